"""The emitted controller format: validation of bad files and the lookup control law."""

from __future__ import annotations

import copy
import dataclasses
import json
import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.controller import (
    BeyondHorizonError,
    ControllerFormatError,
    UncoveredStartError,
    load,
)

TERMINAL = {
    "x_eq": [3.0, 0.0],
    "u_eq": [0.0],
    "K": [[-1.0, -2.0]],
    "P": [[1.5, 0.5], [0.5, 1.0]],
    "level": 0.5,
}


def _document(terminal: bool = False) -> dict:
    """A toy file; ``terminal``: with today's optional fields (else as files before them)."""
    return _base() | (
        {"terminal": copy.deepcopy(TERMINAL), "feedback_period": 0.0} if terminal else {}
    )


def _base() -> dict:
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
    index, ratio = controller.select(x0)
    np.testing.assert_array_equal(index, [0, 1, 0])
    np.testing.assert_allclose(ratio, [0.2 * np.sqrt(2), 0.1 * np.sqrt(2) / 0.5, 1.6 * np.sqrt(2)])
    single, single_ratio = controller.select(x0[1])
    assert int(single) == 1 and single_ratio == pytest.approx(ratio[1])


def test_control_law_interpolates_and_clips(tmp_path):
    controller = load(_write(tmp_path, _document()))
    index, _ = controller.select(np.array([[0.0, 0.0]]))
    x = np.array([[0.25, 0.5]])  # exactly on the reference at t = 0.25
    np.testing.assert_allclose(controller(0.25, x, index), [[0.5]])
    np.testing.assert_allclose(controller(0.75, np.array([[0.75, 1.5]]), index), [[-0.5]])
    far = np.array([[0.25 + 2.0, 0.5]])  # K e = -2 -> 0.5 - 2 clipped to -1
    np.testing.assert_allclose(controller.unclipped(0.25, far, index), [[-1.5]])
    np.testing.assert_allclose(controller(0.25, far, index), [[-1.0]])


def test_a_mixed_batch_is_each_row_alone_and_a_bad_index_is_refused(tmp_path):
    controller = load(_write(tmp_path, _document()))
    x = np.array([[0.25, 0.5], [3.1, 0.0], [2.0, 0.1], [0.5, -0.2]])
    index = np.array([0, 1, 0, 1])
    batch = controller(0.25, x, index)
    for row, i in enumerate(index):
        np.testing.assert_array_equal(batch[row], controller(0.25, x[row], np.array(i)))
    np.testing.assert_array_equal(
        controller(0.25, x, np.ones(4, dtype=int)),
        [controller(0.25, row, np.array(1)) for row in x],
    )
    for bad in (2, -1):
        with pytest.raises(IndexError, match=f"trajectory index {bad} out of range"):
            controller(0.25, x, np.array([0, bad, 0, 1]))
        with pytest.raises(IndexError, match=f"trajectory index {bad} out of range"):
            controller.gains(0.25, np.array([bad]))
    with pytest.raises(IndexError, match="must be integers, found dtype float64"):
        controller.metric(0.25, np.array([0.5]))


def test_the_controller_is_immutable_and_with_gain_builds_a_new_one(tmp_path):
    controller = load(_write(tmp_path, _document()))
    with pytest.raises(dataclasses.FrozenInstanceError):
        controller.K = np.zeros((1, 2))  # type: ignore[misc]
    with pytest.raises(ValueError, match="read-only"):
        controller.K[0, 0] = 5.0
    open_loop = controller.with_gain(0.0)
    np.testing.assert_array_equal(open_loop.K, 0.0)
    np.testing.assert_array_equal(controller.K, [[-1.0, -2.0]])  # the original is unchanged
    far, index = np.array([[2.25, 0.5]]), np.array([0])
    np.testing.assert_allclose(open_loop.unclipped(0.25, far, index), [[0.5]])
    np.testing.assert_allclose(controller.unclipped(0.25, far, index), [[-1.5]])
    assert not hasattr(controller, "follow")


def test_a_file_loaded_again_is_parsed_again_only_when_its_bytes_changed(tmp_path):
    path = _write(tmp_path, _document())
    first = load(path)
    assert load(path) is first  # same path, same bytes: the same immutable controller
    document = _document()
    document["trajectories"][0]["radius"] = 0.75
    _write(tmp_path, document)  # same path, other bytes
    edited = load(path)
    assert edited is not first and edited.trajectories[0].radius == 0.75
    (tmp_path / "controller.json").write_text("{")
    for _ in range(2):  # a bad file is refused every time, never served from before
        with pytest.raises(ControllerFormatError, match="invalid JSON"):
            load(path)
    copies = []
    for i in range(6):  # same bytes at other paths: each its own controller (its source)
        copy = tmp_path / f"copy{i}.json"
        copy.write_text(json.dumps(_document()))
        copies.append(load(copy))
        assert copies[-1].source == str(copy)
    assert load(tmp_path / "copy5.json") is copies[5]  # among the last four loaded
    assert load(tmp_path / "copy0.json") is not copies[0]  # evicted: parsed again


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
        (set_(["format"], "safety-controller/3"), "format: found 'safety-controller/3'"),
        (set_(["feedback", "K"], [[1.0, 2.0, 3.0]]), "feedback.K: found 'shape (1, 3)'"),
        (set_(["trajectories", 1, "x0"], [1.0]), "trajectories[1].x0: found 'shape (1,)'"),
        (set_(["trajectories", 0, "x_ref"], [[0.0, 0.0]]), "trajectories[0].x_ref: found"),
        (set_(["feedback", "rate"], float("nan")), "feedback.rate: found nan; expected a finite"),
        (set_(["trajectories"], []), "trajectories: found 'an empty list'"),
        # values of the right type that no valid controller has (issue 14.4)
        (
            set_(["trajectories", 0, "radius"], -1.0),
            "trajectories[0].radius: found -1.0; expected a number > 0",
        ),
        (
            set_(["trajectories", 1, "radius"], 0),
            "trajectories[1].radius: found 0.0; expected a number > 0",
        ),
        (set_(["Ts"], 0.0), "Ts: found 0.0; expected a number > 0"),
        (set_(["Ts"], -0.1), "Ts: found -0.1; expected a number > 0"),
        (
            set_(["input_bounds", "lower"], [2.0]),
            "input_bounds.lower[0]: found 2.0; expected <= upper",
        ),
        (
            set_(["feedback", "P"], [[1.0, 0.0], [0.0, -1.0]]),
            "feedback.P: found 'smallest eigenvalue -1'",
        ),
        (
            set_(["feedback", "P"], [[1.0, 0.5], [0.0, 1.0]]),
            "feedback.P: found 'a non-symmetric matrix'",
        ),
        (set_(["feedback", "rate"], -0.5), "feedback.rate: found -0.5; expected a number > 0"),
        (
            set_(
                ["trajectories", 0, "t"], [0.0, 0.1, 0.3, 0.2, *np.linspace(0.4, 1.0, 7).tolist()]
            ),
            "trajectories[0].t: found 'times that do not increase'",
        ),
        (
            set_(["trajectories", 0, "T"], 2.0),
            "trajectories[0].t: found '[0 .. 1]'; expected times from 0 to T = 2",
        ),
        (
            set_(["trajectories", 0, "u_ref"], [[0.5]]),
            "trajectories[0].u_ref: found '1 rows'; expected T / Ts",
        ),
        (
            set_(["state_names"], "pv"),
            "state_names: found 'pv'; expected a non-empty list of names",
        ),
        (
            set_(["state_names"], ["p", "p"]),
            "state_names: found ['p', 'p']; expected distinct names",
        ),
        (
            set_(["trajectories", 0, "radius"], True),
            "trajectories[0].radius: found True; expected a number",
        ),
        # wrong types that used to raise a raw exception
        (
            set_(["trajectories", 0, "T"], "abc"),
            "trajectories[0].T: found 'abc'; expected a number",
        ),
        (set_(["state_names"], 4), "state_names: found 4; expected a non-empty list of names"),
        (set_(["input_bounds"], []), "input_bounds: found 'a list'; expected a JSON object"),
        (set_(["trajectories"], 3), "trajectories: found 3; expected a list of trajectories"),
        (
            set_(["trajectories"], "abc"),
            "trajectories: found 'abc'; expected a list of trajectories",
        ),
        (set_(["trajectories", 0], 7), "trajectories[0]: found 'int'; expected a JSON object"),
        (set_(["feedback", "K"], [[1.0, "x"]]), "feedback.K: found 'x'; expected numbers"),
        (set_(["feedback", "K"], [[1.0], [2.0, 3.0]]), "feedback.K: found 'ragged lists'"),
        (
            set_(["trajectories", 0, "x0"], [1.0, 10**400]),
            "trajectories[0].x0: found 'a number too large",
        ),
        (set_(["interpolation_error_P_norm"], -1.0), "interpolation_error_P_norm: found -1.0"),
    ]


@pytest.mark.parametrize(("mutate", "message"), _mutations())
def test_bad_files_are_refused_with_the_field(tmp_path, mutate, message):
    document = copy.deepcopy(_document())
    mutate(document)
    with pytest.raises(ControllerFormatError) as error:
        load(_write(tmp_path, document))
    assert message in str(error.value)
    assert "controller.json" in str(error.value)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b'{"format": "\xff\xfe"}', "not UTF-8 text"),
        (b"[" * 100_000 + b"]" * 100_000, "nested too deeply"),
        (b'{"Ts": ' + b"7" * 5000 + b"}", "invalid JSON number"),
        (b"", "invalid JSON at line 1"),
        (b"[1, 2]", "(top level): found 'a list'; expected a JSON object"),
    ],
)
def test_bytes_that_are_not_a_controller_document_are_refused(tmp_path, content, message):
    path = tmp_path / "controller.json"
    path.write_bytes(content)
    with pytest.raises(ControllerFormatError, match=re.escape(message)):
        load(path)


def test_a_huge_float_literal_is_refused_as_not_finite(tmp_path):
    document = _document()
    text = json.dumps(document).replace('"Ts": 0.5', '"Ts": ' + "9" * 5000 + ".0")
    path = tmp_path / "controller.json"
    path.write_text(text)
    with pytest.raises(ControllerFormatError, match="Ts: found inf; expected a finite number"):
        load(path)


def test_invalid_json_names_line_and_column(tmp_path):
    path = tmp_path / "controller.json"
    path.write_text('{"format": \n oops}')
    with pytest.raises(ControllerFormatError, match="line 2, column 2"):
        load(path)


# Property: whatever is done to a valid file, load() either accepts it or raises
# ControllerFormatError (never a raw exception, never a hang: each example has a deadline).

JSON_VALUES = st.recursive(
    st.none()
    | st.booleans()
    | st.integers()
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=6),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4)
    ),
    max_leaves=12,
)


def _paths(node, prefix=()):
    """Every path (tuple of keys and indices) to a node below the document's root."""
    items = (
        node.items()
        if isinstance(node, dict)
        else enumerate(node)
        if isinstance(node, list)
        else ()
    )
    for key, child in items:
        yield (*prefix, key)
        yield from _paths(child, (*prefix, key))


PATHS = list(_paths(_document(terminal=True)))


def _parent(document, path):
    target = document
    for key in path[:-1]:
        target = target[key]
    return target


@settings(
    max_examples=300, deadline=2000, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    path=st.sampled_from(PATHS),
    action=st.sampled_from(["delete", "replace", "retype", "truncate", "flip"]),
    value=JSON_VALUES,
    cut=st.floats(0.0, 1.0),
)
def test_mutated_files_raise_nothing_but_controller_format_error(
    tmp_path, path, action, value, cut
):
    _load_mutated(tmp_path, _document(terminal=True), path, action, value, cut)


def _load_mutated(tmp_path, document, path, action, value, cut):
    """Apply ``action`` at ``path`` of ``document``; ``load`` must refuse the result with
    ``ControllerFormatError`` or accept a usable controller."""
    parent, key = _parent(document, path), path[-1]
    if action == "delete":
        del parent[key]
    elif action == "replace":
        parent[key] = value
    elif action == "retype":  # the same content under another JSON type
        old = parent[key]
        parent[key] = json.dumps(old) if not isinstance(old, str) else [old]
    content = json.dumps(document).encode()
    if action == "truncate":
        content = content[: int(cut * len(content))]
    elif action == "flip":
        position = min(int(cut * len(content)), len(content) - 1)
        content = content[:position] + bytes([content[position] ^ 0xA5]) + content[position + 1 :]
    file = tmp_path / "controller.json"
    file.write_bytes(content)
    try:
        controller = load(file)
    except ControllerFormatError as error:
        assert "controller.json" in str(error)
        return
    # accepted: it must then be a usable controller
    index, ratio = controller.select(controller.trajectories[0].x0)
    assert np.isfinite(controller(0.0, controller.trajectories[0].x0, index)).all()
    assert ratio >= 0


def test_files_without_the_optional_fields_still_load(tmp_path):
    controller = load(_write(tmp_path, _document()))
    assert controller.terminal is None and controller.feedback_period == 0.0


def test_select_strict_refuses_uncovered_starts(tmp_path):
    controller = load(_write(tmp_path, _document()))
    index, ratio = controller.select(np.array([[0.2, 0.0], [1.6, 0.0]]))
    assert ratio[0] < 1 <= ratio[1]  # the second start is outside every ball
    controller.select(np.array([0.2, 0.0]), strict=True)  # covered: accepted
    with pytest.raises(UncoveredStartError, match=r"start \[1.6, 0.0\] .* ratio 2.26 >= 1"):
        controller.select(np.array([[0.2, 0.0], [1.6, 0.0]]), strict=True)


def test_past_T_the_law_switches_to_the_terminal_controller_or_refuses(tmp_path):
    x = np.array([[3.2, 0.1], [0.5, 0.5]])
    index = np.array([1, 0])
    without = load(_write(tmp_path, _document()))
    with pytest.raises(BeyondHorizonError, match="no terminal controller"):
        without(1.5, x, index)
    with_terminal = load(_write(tmp_path, _document(terminal=True)))
    u = with_terminal(1.5, x, index)
    expected = np.clip(0.0 + (x - [3.0, 0.0]) @ np.array([[-1.0, -2.0]]).T, -1.0, 1.0)
    np.testing.assert_allclose(u, expected)
    # up to T both laws agree
    np.testing.assert_allclose(with_terminal(1.0, x, index), without(1.0, x, index))


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (
            lambda d: d["terminal"].update(level=0.0),
            r"terminal.level: found 0.0; expected a number > 0",
        ),
        (
            lambda d: d["terminal"].update(P=[[1.0, 0.0], [0.0, -1.0]]),
            "terminal.P: found 'smallest eigenvalue",
        ),
        (lambda d: d["terminal"].pop("u_eq"), "terminal.u_eq: found 'nothing"),
        (
            lambda d: d.update(feedback_period=-0.01),
            "feedback_period: found -0.01; expected a number >= 0",
        ),
    ],
)
def test_bad_terminal_blocks_are_refused(tmp_path, mutate, message):
    document = _document(terminal=True)
    mutate(document)
    with pytest.raises(ControllerFormatError, match=re.escape(message)):
        load(_write(tmp_path, document))


# safety-controller/2: a gain per sample interval and a metric per sample on each trajectory.

FUNNEL_K = [[[-1.0, -2.0]], [[-3.0, -1.0]]]  # (N = 2, m = 1, n = 2)
FUNNEL_P = [[[2.0, 0.0], [0.0, 1.0]], [[4.0, 1.0], [1.0, 2.0]], [[1.0, 0.0], [0.0, 1.0]]]


def _funnel_document() -> dict:
    """The toy file as /2: trajectory 0 with its own ``K[k]``, ``P[k]``; trajectory 1 with
    ``K = 0`` and ``P = 8 I`` (no ``rate``: 0)."""
    document = _base()
    del document["feedback"]
    document |= {"format": "safety-controller/2", "metric_interpolation": "inverse-linear"}
    first, second = document["trajectories"]
    first |= {"K": FUNNEL_K, "P": FUNNEL_P, "rate": 0.0}
    second |= {"K": [[[0.0, 0.0]]] * 2, "P": (8 * np.eye(2)[None].repeat(3, axis=0)).tolist()}
    return copy.deepcopy(document)  # no list shared with FUNNEL_K, FUNNEL_P or another field


def test_funnel_file_selects_in_each_initial_metric_and_flies_the_gain_of_the_interval(tmp_path):
    controller = load(_write(tmp_path, _funnel_document()))
    assert controller.funnel and controller.K is None and controller.P is None
    x0 = np.array([[0.2, 0.0], [3.1, 0.1]])
    index, ratio = controller.select(x0)
    np.testing.assert_array_equal(index, [0, 1])
    # ||x0 - x0_i||_{P_i[0]} / radius_i: sqrt(2 * 0.04) / 1 and sqrt(8 * 0.02) / 0.5
    np.testing.assert_allclose(ratio, [np.sqrt(0.08), np.sqrt(0.16) / 0.5])
    e = np.array([[0.1, 0.2]])
    x = np.array([[0.25, 0.5]]) + e  # the reference at t = 0.25 is (0.25, 0.5), u_ref 0.5
    np.testing.assert_allclose(controller.unclipped(0.25, x, [0]), [[0.0]], atol=1e-15)
    x = np.array([[0.75, 1.5]]) + e  # interval 1: u_ref -0.5, K = (-3, -1)
    np.testing.assert_allclose(controller.unclipped(0.75, x, [0]), [[-0.5 - 0.3 - 0.2]])
    np.testing.assert_allclose(controller(0.75, x, [0]), [[-1.0]])  # clipped
    np.testing.assert_allclose(controller.unclipped(0.75, x + 3, [1]), [[0.0]], atol=1e-15)
    open_loop = controller.with_gain(0.0)
    np.testing.assert_allclose(open_loop.unclipped(0.75, x, [0]), [[-0.5]])
    np.testing.assert_allclose(controller.trajectories[0].K, FUNNEL_K)  # unchanged
    with pytest.raises(UncoveredStartError, match="coverage ratio 2.26"):
        controller.select(np.array([1.6, 0.0]), strict=True)  # sqrt(2 * 1.6^2) from ball 0
    with pytest.raises(BeyondHorizonError, match="no terminal controller"):
        controller(1.5, x, np.array([0]))  # no terminal block: the law refuses t > T


def test_funnel_metric_is_inverse_linear_between_samples(tmp_path):
    controller = load(_write(tmp_path, _funnel_document()))
    P = np.array(FUNNEL_P)
    Q = np.linalg.inv(P)
    for t, expected in ((0.0, P[0]), (0.5, P[1]), (1.0, P[2]), (2.0, P[2])):
        np.testing.assert_allclose(controller.metric(t, np.array(0)), expected, rtol=1e-12)
    s = 0.3  # t = 0.5 + 0.3 * 0.5 on interval 1
    expected = np.linalg.inv((1 - s) * Q[1] + s * Q[2])
    np.testing.assert_allclose(controller.metric(0.65, np.array([0])), [expected], rtol=1e-12)
    assert not np.allclose(expected, (1 - s) * P[1] + s * P[2])  # not linear in P
    grid = controller.trajectories[0].metric(np.array([0.0, 0.65]), controller.Ts)
    np.testing.assert_allclose(grid, [P[0], expected], rtol=1e-12)
    constant = load(_write(tmp_path, _document()))  # a /1 file: P(t) = P
    np.testing.assert_array_equal(
        constant.metric(0.65, np.array([0, 1])), [np.diag([2.0, 1.0])] * 2
    )


def _funnel_mutations():
    def trajectory(key, value):
        return lambda d: d["trajectories"][0].__setitem__(key, value)

    bad_P = [FUNNEL_P[0], [[1.0, 2.0], [2.0, 1.0]], FUNNEL_P[2]]  # eigenvalues 3, -1
    return [
        (lambda d: d["trajectories"][0].pop("K"), "trajectories[0].K: found 'nothing"),
        (lambda d: d["trajectories"][1].pop("P"), "trajectories[1].P: found 'nothing"),
        (trajectory("K", FUNNEL_K[:1]), "trajectories[0].K: found 'shape (1, 1, 2)'"),
        (trajectory("P", FUNNEL_P[:2]), "trajectories[0].P: found 'shape (2, 2, 2)'"),
        (trajectory("P", bad_P), "trajectories[0].P[1]: found 'smallest eigenvalue -1'"),
        (trajectory("rate", -0.5), "trajectories[0].rate: found -0.5; expected a number >= 0"),
        (lambda d: d.pop("metric_interpolation"), "metric_interpolation: found 'nothing"),
        (lambda d: d.update(metric_interpolation="linear"), "expected 'inverse-linear'"),
        (lambda d: d.update(feedback={"K": [[1.0]]}), "feedback.P: found 'nothing"),
    ]


@pytest.mark.parametrize(("mutate", "message"), _funnel_mutations())
def test_bad_funnel_files_are_refused_with_the_field(tmp_path, mutate, message):
    document = _funnel_document()
    mutate(document)
    with pytest.raises(ControllerFormatError, match=re.escape(message)):
        load(_write(tmp_path, document))


FUNNEL_PATHS = list(_paths(_funnel_document()))


@settings(
    max_examples=200, deadline=2000, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    path=st.sampled_from(FUNNEL_PATHS),
    action=st.sampled_from(["delete", "replace", "retype", "truncate", "flip"]),
    value=JSON_VALUES,
    cut=st.floats(0.0, 1.0),
)
def test_mutated_funnel_files_raise_nothing_but_controller_format_error(
    tmp_path, path, action, value, cut
):
    _load_mutated(tmp_path, _funnel_document(), path, action, value, cut)


# NaN and infinity: the law refuses them, naming the field and component (issue 27, item 8).


def test_select_refuses_a_nan_start_instead_of_trajectory_0_at_ratio_nan(tmp_path):
    controller = load(_write(tmp_path, _document()))
    for strict in (True, False):
        with pytest.raises(ValueError, match=re.escape("x0[0] (p) = nan; expected a finite start")):
            controller.select(np.array([np.nan, 0.0]), strict=strict)
    with pytest.raises(ValueError, match=re.escape("x0[1, 1] (v) = -inf; expected a finite")):
        controller.select(np.array([[0.2, 0.0], [0.1, -np.inf]]))


def test_the_law_refuses_a_nan_state_or_time_instead_of_sending_nan_to_the_actuator(tmp_path):
    for document in (_document(terminal=True), _funnel_document()):
        controller = load(_write(tmp_path, document))
        index = np.array([0, 0])
        with pytest.raises(ValueError, match=re.escape("x[0] (p) = nan; expected a finite state")):
            controller(0.25, np.array([np.nan, 0.5]), np.array(0))
        with pytest.raises(ValueError, match=re.escape("x[1, 1] (v) = inf; expected a finite")):
            controller(0.25, np.array([[0.25, 0.5], [0.25, np.inf]]), index)
        for t in (np.nan, np.inf, -np.inf):
            with pytest.raises(ValueError, match=re.escape(f"t = {t}; expected a finite time")):
                controller(t, np.array([0.25, 0.5]), np.array(0))


SPECIAL = st.sampled_from([np.nan, np.inf, -np.inf])
COMPONENT = st.floats(-1e6, 1e6) | SPECIAL


@settings(
    max_examples=300, deadline=2000, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    funnel=st.booleans(),
    t=st.floats(-1.0, 3.0) | SPECIAL,
    x=st.lists(st.lists(COMPONENT, min_size=2, max_size=2), min_size=1, max_size=3),
    data=st.data(),
)
def test_the_law_gives_finite_inputs_within_bounds_or_refuses_naming_the_field(
    tmp_path, funnel, t, x, data
):
    """Property: for any start and state (finite, NaN or infinite components) and any time,
    ``select`` and the law return finite values (inputs within their bounds) or raise
    ``ValueError`` naming the non-finite field (``BeyondHorizonError`` past ``T``)."""
    controller = load(_write(tmp_path, _funnel_document() if funnel else _document(True)))
    x = np.array(x)
    bad = [f"[{i}, {j}] ({'pv'[j]})" for i, j in zip(*np.nonzero(~np.isfinite(x)), strict=True)]
    try:
        index, ratio = controller.select(x)
    except ValueError as error:
        assert bad and str(error).startswith(f"x0{bad[0]} = ")
    else:
        assert not bad and np.all(np.isfinite(ratio)) and np.all(ratio >= 0)
    index = np.array(data.draw(st.lists(st.integers(0, 1), min_size=len(x), max_size=len(x))))
    try:
        u = controller(t, x, index)
    except BeyondHorizonError:
        assert funnel and t > 1.0  # the /2 toy has no terminal controller
    except ValueError as error:
        if np.isfinite(t) and t >= 0:
            assert bad and str(error).startswith(f"x{bad[0]} = ")
        elif np.isfinite(t):
            assert str(error) == f"t = {t:g} s; expected a time >= 0 (s) since the start"
        else:
            assert str(error).startswith(f"t = {t}; ")
    else:
        assert np.isfinite(t) and t >= 0 and not bad
        assert np.all((controller.lower <= u) & (u <= controller.upper))


# At the prompt (issue 31, item 5): short reprs, Python scalars for one state, readable errors.


def _named(document: dict) -> dict:
    for i, item in enumerate(document["trajectories"]):
        item["name"] = f"demo_{i + 1:02d}"
    return document


@pytest.mark.parametrize("funnel", [False, True])
def test_repr_is_a_few_lines_with_the_trajectories_by_index_and_name(tmp_path, funnel):
    document = _named(_funnel_document() if funnel else _document(terminal=True))
    document["trajectories"] *= 20  # 40 trajectories: still a few lines
    controller = load(_write(tmp_path, document))
    text = repr(controller)
    lines = text.splitlines()
    assert len(lines) < 15 and max(map(len, lines)) < 200, text
    assert f"safety-controller/{2 if funnel else 1}, scenario 'toy'" in lines[0]
    assert "trajectories (40, index: name): 0: demo_01, 1: demo_02," in text
    assert "39: demo_02" in text and "horizons T: 1 s" in text
    assert ("certificate: funnel" if funnel else "certificate: constant") in text
    assert ("terminal: no" if funnel else "terminal: yes") in text
    assert "feedback period: 0 (continuous)" in text
    assert controller.trajectories[0].name == "demo_01"
    assert repr(controller.trajectories[1]) == (
        "ReferenceTrajectory('demo_02', T=1 s, radius=0.5, rate="
        + ("0" if funnel else "0.5")
        + ", N=2 samples, x0=[3, 0])"
    )
    if not funnel:
        assert repr(controller.terminal) == "TerminalController(x_eq=[3, 0], u_eq=[0], level=0.5)"


def test_trajectory_names_are_optional_and_must_be_strings(tmp_path):
    controller = load(_write(tmp_path, _document()))
    assert [tr.name for tr in controller.trajectories] == [None, None]
    assert "trajectories (2): 0, 1" in repr(controller)
    document = _document()
    document["trajectories"][1]["name"] = 7
    with pytest.raises(ControllerFormatError, match=re.escape("trajectories[1].name: found 7")):
        load(_write(tmp_path, document))


def test_select_on_one_state_gives_a_python_int_and_float_and_a_batch_arrays(tmp_path):
    controller = load(_write(tmp_path, _document()))
    index, ratio = controller.select(np.array([2.9, 0.0]))
    assert type(index) is int and type(ratio) is float and index == 1
    assert ratio == pytest.approx(0.1 * np.sqrt(2) / 0.5)
    index, ratio = controller.select([[2.9, 0.0]])  # a batch of one stays a batch
    assert index.shape == (1,) and ratio.shape == (1,)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (
            lambda c: c.select(np.zeros(3)),
            "x0 has shape (3,); expected (2,) for one state (p, v) or (B, 2) for a batch of B",
        ),
        (lambda c: c.select(np.float64(0.0)), "x0 has shape (); expected (2,) for one state"),
        (lambda c: c.select(np.zeros((4, 1))), "x0 has shape (4, 1); expected (2,)"),
        (lambda c: c(0.5, np.zeros(3), 0), "x has shape (3,); expected (2,) for one state (p, v)"),
        (lambda c: c(0.5, np.zeros((2, 3)), np.array([0, 1])), "x has shape (2, 3); expected"),
        (lambda c: c(-0.1, np.zeros(2), 0), "t = -0.1 s; expected a time >= 0 (s) since the start"),
        (lambda c: c(-1e-12, np.zeros(2), 0), "t = -1e-12 s; expected a time >= 0"),
    ],
)
def test_wrong_shapes_and_negative_times_are_value_errors_naming_what_is_expected(
    tmp_path, call, message
):
    for document in (_document(terminal=True), _funnel_document()):
        controller = load(_write(tmp_path, document))
        with pytest.raises(ValueError, match=re.escape(message)):
            call(controller)
