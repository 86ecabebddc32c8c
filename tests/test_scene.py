"""The synthetic scene, its depth sensor, and the Fig. 5 pipeline's check."""

import numpy as np
import pytest

import logsph_trace as lt
from logsph_trace.scene import Box, Scene, table_scene


def test_cast_finds_the_nearest_box():
    scene, _, _ = table_scene()
    direction = np.array([[0.0, 0.2, 1.0]])  # over the table and the object, onto the wall
    distance, which = scene.cast([0.0, 0.0, 0.0], direction)
    assert which[0] == scene.index("wall")
    assert distance[0] == pytest.approx(3.5)  # in units of the (unnormalised) direction
    distance, which = scene.cast([0.0, -0.4, 0.0], [[0.0, 0.0, 1.0]])
    assert which[0] == scene.index("object") and distance[0] == pytest.approx(1.55)
    distance, which = scene.cast([0.0, 0.0, 0.0], [[0.0, 0.0, -1.0]])
    assert which[0] == -1 and np.isinf(distance[0])


def test_depth_points_lie_on_their_boxes():
    scene, _, _ = table_scene()
    points, labels, depth = scene.depth_points(width=64, height=48)
    assert depth.shape == (48, 64) and points.shape[0] == labels.shape[0]
    assert set(labels.tolist()) == {0, 1, 2}
    low, high = scene.low[labels], scene.high[labels]
    assert np.all((points >= low - 1e-9) & (points <= high + 1e-9))


def test_the_object_is_what_the_person_looks_at():
    # The Fig. 5 pipeline (bench/fig5.py) on a small image: the object is the
    # first occupied cell on the gaze and the most probable fixation.
    from bench.fig5 import GRID_ARGS, run

    result = run(lt.Grid(**GRID_ARGS), scans=3, width=320, height=240)
    assert result["top_is_object"]
    assert result["fixation_top_is_object"]


def test_bad_scene():
    with pytest.raises(ValueError, match="at least one box"):
        Scene([])
    with pytest.raises(ValueError, match="low < high"):
        Scene([Box("flat", (0, 0, 0), (1, 0, 1))])
    with pytest.raises(ValueError, match="no box named 'chair'"):
        table_scene()[0].index("chair")
