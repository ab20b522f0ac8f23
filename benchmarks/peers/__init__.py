"""The frameworks a user would serve the model with instead of the service (benchmarks/bench_peers.py).

Every peer computes its answer with the service's own domain functions (``pipeline.Pipeline``),
so answers are identical and only the serving differs.
"""
