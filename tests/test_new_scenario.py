"""``python -m pipeline new NAME --like TEMPLATE`` and ``demos``' report (issue 31, item 1): a
user's own scenario starts from a shipped one, is found by name from the current directory, and
flies and certifies without edits."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from pipeline.demonstrations.pilot import PilotConfig, load_pilot
from pipeline.model.scenario import load_scenario
from pipeline.runtime.cli import main
from pipeline.runtime.scaffold import PILOT_FIELDS, TEMPLATES


def _new(name: str, *like: str) -> int:
    return main(["new", name, *(("--like", like[0]) if like else ())])


@pytest.mark.parametrize("like", TEMPLATES)
def test_new_writes_a_scenario_that_loads_with_its_pilot(
    like: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    assert _new("my_robot", like) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[-2:] == [
        "  python -m pipeline demos my_robot",
        "  python -m pipeline synthesize my_robot",
    ]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scenarios"]  # nothing else written
    folder = tmp_path / "scenarios" / "my_robot"
    assert sorted(p.name for p in (tmp_path / "scenarios").iterdir()) == ["my_robot"]  # no temp
    assert sorted(p.name for p in folder.iterdir()) == ["demos", "pilot.py", "scenario.yaml"]
    assert folder.stat().st_mode == (folder / "demos").stat().st_mode  # not a temp dir's 0700
    scenario = load_scenario("my_robot", check_demos=False)  # found by name, from ./scenarios
    assert scenario.path == folder / "scenario.yaml"
    assert scenario.name == "my_robot" and scenario.demos == ()
    shipped = load_scenario(like, check_demos=False)
    assert scenario.state_names == shipped.state_names
    config = load_pilot(scenario).config
    text = (folder / "pilot.py").read_text()
    for field in dataclasses.fields(PilotConfig):  # each field set in CONFIG or listed below it
        set_here = re.search(rf"^    {field.name}=", text, flags=re.MULTILINE)
        listed = re.search(rf"^#   {field.name} = ", text, flags=re.MULTILINE)
        assert bool(set_here) != bool(listed), field.name
        assert set_here or field.default is not dataclasses.MISSING
    assert config.variant_flights == ()
    assert max(text.splitlines(), key=len).__len__() <= 100


def test_every_pilot_field_is_explained() -> None:
    assert set(PILOT_FIELDS) == {field.name for field in dataclasses.fields(PilotConfig)}


@pytest.mark.slow
def test_new_then_demos_then_synthesize_certifies(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The double-integrator template (the cheapest: about 2 s of demos and 10 s of synthesis
    here) flies 4 demos and certifies as written."""
    monkeypatch.chdir(tmp_path)
    assert _new("my_point") == 0  # --like double_integrator by default
    capsys.readouterr()
    assert main(["demos", "my_point"]) == 0
    out = capsys.readouterr().out
    assert re.fullmatch(
        r"wrote demo_01\.\.04 \(T \d+\.\d-\d+\.\d s, all valid\); updated scenario\.yaml demos: "
        r"in scenarios/my_point\n",
        out,
    ), out
    assert len(load_scenario("my_point").demos) == 4
    assert main(["synthesize", "my_point", "--samples", "200", "--quiet"]) == 0
    assert "certified" in capsys.readouterr().out
    assert (tmp_path / "reports" / "my_point" / "controller.json").is_file()


def test_demos_of_one_flight_says_so(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    assert _new("one") == 0
    pilot = tmp_path / "scenarios" / "one" / "pilot.py"
    pilot.write_text(pilot.read_text().replace("grid=(('y', 2), ('x', 2)),", "grid=(),"))
    capsys.readouterr()
    assert main(["demos", "one"]) == 0
    assert re.fullmatch(
        r"wrote demo_01 \(T \d+\.\d s, all valid\); updated scenario\.yaml demos: "
        r"in scenarios/one\n",
        capsys.readouterr().out,
    )


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (
            ["new", "my robot"],
            "error: invalid scenario name 'my robot'; expected a letter, then "
            "letters, digits or '_' (at most 64), e.g. my_robot",
        ),
        (
            ["new", "../up"],
            "error: invalid scenario name '../up'; expected a letter, then "
            "letters, digits or '_' (at most 64), e.g. my_robot",
        ),
        (
            ["new", "car", "--like", "dubins"],
            "error: unknown template --like 'dubins'; expected "
            "one of: double_integrator, unicycle_slalom, quadrotor_hill_flythrough",
        ),
        (
            ["new", "quadrotor_hill_flythrough"],
            "error: 'quadrotor_hill_flythrough' is a shipped scenario's name; "
            "expected another name (yours would hide it)",
        ),
    ],
)
def test_new_refuses_in_one_line(
    argv: list[str],
    message: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    assert capsys.readouterr().err == message + "\n"
    assert list(tmp_path.iterdir()) == []


def test_new_refuses_an_existing_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    mine = tmp_path / "scenarios" / "car"
    mine.mkdir(parents=True)
    (mine / "notes.txt").write_text("mine")
    assert _new("car", "unicycle_slalom") == 2
    assert capsys.readouterr().err == (
        f"error: {mine} already exists; expected a new name, or remove that folder first\n"
    )
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]


def test_a_failed_write_leaves_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Writing into a staging folder renamed into place: a failure mid-way (here the second
    file) leaves neither the target nor the staging folder, nor a ./scenarios made for it."""
    monkeypatch.chdir(tmp_path)
    write_text = Path.write_text

    def failing(self: Path, text: str, *args: object, **kwargs: object) -> int:
        if self.name == "pilot.py":
            raise OSError(28, "No space left on device", str(self))
        return write_text(self, text, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(Path, "write_text", failing)
    assert main(["new", "car"]) == 2
    assert capsys.readouterr().err.startswith(f"error: cannot write {tmp_path}/scenarios/.car.")
    assert list(tmp_path.iterdir()) == []
