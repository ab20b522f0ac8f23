"""Camera matrices: a pinhole K is accepted, everything else is refused with what to fix."""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.pose import as_camera_matrix, camera_matrix_problems

GOOD = [[572.0, 0.0, 320.0], [0.0, 572.0, 240.0], [0.0, 0.0, 1.0]]


def test_a_pinhole_matrix_is_accepted() -> None:
    assert camera_matrix_problems(GOOD) == []
    assert np.array_equal(as_camera_matrix(GOOD), np.array(GOOD))


@pytest.mark.parametrize(
    ("matrix", "says"),
    [
        ([[572.0, 0.0, 320.0], [0.0, 572.0, 240.0]], "3 rows of 3"),
        ([[572.0, 0.0], [0.0, 572.0], [0.0, 0.0]], "3 rows of 3"),
        ([[math.nan, 0.0, 320.0], [0.0, 572.0, 240.0], [0.0, 0.0, 1.0]], "finite"),
        ([[572.0, 0.0, math.inf], [0.0, 572.0, 240.0], [0.0, 0.0, 1.0]], "finite"),
        ([[0.0, 0.0, 320.0], [0.0, 572.0, 240.0], [0.0, 0.0, 1.0]], "fx"),
        ([[572.0, 0.0, 320.0], [0.0, -1.0, 240.0], [0.0, 0.0, 1.0]], "fy"),
        ([[572.0, 0.5, 320.0], [0.0, 572.0, 240.0], [0.0, 0.0, 1.0]], "skew"),
        ([[572.0, 0.0, 320.0], [0.0, 572.0, 240.0], [0.0, 0.0, 2.0]], "last row"),
        ([[572.0, 0.0, 320.0], [0.0, 572.0, 240.0], [0.1, 0.0, 1.0]], "last row"),
    ],
)
def test_a_malformed_matrix_is_refused_saying_why(matrix: list, says: str) -> None:
    problems = camera_matrix_problems(matrix)
    assert problems and says in " ".join(problems)
    with pytest.raises(ValueError, match=says):
        as_camera_matrix(matrix)
