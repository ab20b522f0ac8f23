"""Feedback on served predictions: labels in, live coverage and field calibrations out."""
