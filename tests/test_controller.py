"""The emitted controller format: validation of bad files and the lookup control law."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from pipeline.controller import ControllerFormatError, load


def _document() -> dict:
    t = np.linspace(0.0, 1.0, 11)
    return {
        "format": "safety-controller/1",
        "scenario": "toy",
        "state_names": ["p", "v"],
        "input_names": ["a"],
        "Ts": 0.5,
        "input_bounds": {"lower": [-1.0], "upper": [1.0]},
        "feedback": {"K": [[-1.0, -2.0]], "P": [[2.0, 0.0], [0.0, 1.0]], "rate": 0.5},
        "trajectories": [
            {
                "x0": [0.0, 0.0],
                "radius": 1.0,
                "T": 1.0,
                "u_ref": [[0.5], [-0.5]],
                "t": t.tolist(),
                "x_ref": np.stack([t, 2 * t], axis=-1).tolist(),
            },
            {
                "x0": [3.0, 0.0],
                "radius": 0.5,
                "T": 1.0,
                "u_ref": [[0.0], [0.0]],
                "t": t.tolist(),
                "x_ref": np.stack([3 + 0 * t, 0 * t], axis=-1).tolist(),
            },
        ],
    }


def _write(tmp_path, document) -> str:
    path = tmp_path / "controller.json"
    path.write_text(json.dumps(document))
    return str(path)


def test_selects_the_ball_with_the_smallest_scaled_distance(tmp_path):
    controller = load(_write(tmp_path, _document()))
    x0 = np.array([[0.2, 0.0], [2.9, 0.0], [1.6, 0.0]])
    # ||x0 - x0_i||_P / r_i: row 2 is 1.6*sqrt2/1 = 2.26 from the first, 1.4*sqrt2/0.5 = 3.96
    np.testing.assert_array_equal(controller.select(x0), [0, 1, 0])
    np.testing.assert_allclose(
        controller.coverage_ratio(x0), [0.2 * np.sqrt(2), 0.1 * np.sqrt(2) / 0.5, 1.6 * np.sqrt(2)]
    )


def test_control_law_interpolates_and_clips(tmp_path):
    controller = load(_write(tmp_path, _document()))
    controller.select(np.array([[0.0, 0.0]]))
    x = np.array([[0.25, 0.5]])  # exactly on the reference at t = 0.25
    np.testing.assert_allclose(controller(0.25, x), [[0.5]])
    np.testing.assert_allclose(controller(0.75, np.array([[0.75, 1.5]])), [[-0.5]])
    far = np.array([[0.25 + 2.0, 0.5]])  # K e = -2 -> 0.5 - 2 clipped to -1
    np.testing.assert_allclose(controller.unclipped(0.25, far), [[-1.5]])
    np.testing.assert_allclose(controller(0.25, far), [[-1.0]])


def test_calling_before_select_is_an_error(tmp_path):
    controller = load(_write(tmp_path, _document()))
    with pytest.raises(RuntimeError, match="select"):
        controller(0.0, np.zeros((1, 2)))


def _mutations():
    def drop(path):
        def apply(d):
            *parents, last = path
            target = d
            for key in parents:
                target = target[key]
            del target[last]

        return apply

    def set_(path, value):
        def apply(d):
            *parents, last = path
            target = d
            for key in parents:
                target = target[key]
            target[last] = value

        return apply

    return [
        (drop(["feedback"]), "feedback: found 'nothing (missing field)'"),
        (drop(["trajectories", 0, "x_ref"]), "trajectories[0].x_ref: found 'nothing"),
        (set_(["format"], "safety-controller/2"), "format: found 'safety-controller/2'"),
        (set_(["feedback", "K"], [[1.0, 2.0, 3.0]]), "feedback.K: found 'shape (1, 3)'"),
        (set_(["trajectories", 1, "x0"], [1.0]), "trajectories[1].x0: found 'shape (1,)'"),
        (set_(["trajectories", 0, "x_ref"], [[0.0, 0.0]]), "trajectories[0].x_ref: found"),
        (set_(["feedback", "rate"], float("nan")), "feedback.rate: found 'a non-finite value'"),
        (set_(["trajectories"], []), "trajectories: found 'an empty list'"),
    ]


@pytest.mark.parametrize(("mutate", "message"), _mutations())
def test_bad_files_are_refused_with_the_field(tmp_path, mutate, message):
    document = copy.deepcopy(_document())
    mutate(document)
    with pytest.raises(ControllerFormatError) as error:
        load(_write(tmp_path, document))
    assert message in str(error.value)
    assert "controller.json" in str(error.value)


def test_invalid_json_names_line_and_column(tmp_path):
    path = tmp_path / "controller.json"
    path.write_text('{"format": \n oops}')
    with pytest.raises(ControllerFormatError, match="line 2, column 2"):
        load(path)
