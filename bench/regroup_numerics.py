"""One-off (issue 28 item 7): rewrite references to the flat ``pipeline/numerics`` modules to
their subpackages. Idempotent: a path already rewritten is left alone, so it can be re-run over
a branch merged after the move. Run from the repository root: ``python bench/regroup_numerics.py
[files...]`` (default: every tracked ``.py``, ``.md``, ``.toml`` file).

Rewrites ``pipeline.numerics.OLD`` and ``pipeline/numerics/OLD`` (followed by anything but a word
character), ``from pipeline.numerics import OLD``, and the prefixed module names that prose cites
bare (``funnel_law`` -> ``funnel.law``); other bare names (``verify``, ``margins``) are words too
and are left as they are.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

# old module -> (subpackage, new module)
MOVES = {
    "tube": ("tube", "geometry"),
    "tube_radius": ("tube", "radius"),
    "sampled": ("tube", "sampled"),
    "feedback_search": ("tube", "feedback_search"),
    "funnel": ("funnel", "synthesis"),
    "funnel_bounds": ("funnel", "bounds"),
    "funnel_check": ("funnel", "check"),
    "funnel_law": ("funnel", "law"),
    "funnel_lmi": ("funnel", "lmi"),
    "funnel_pieces": ("funnel", "pieces"),
    "cells": ("funnel", "cells"),
    "terminal": ("terminal", "design"),
    "terminal_fit": ("terminal", "fit"),
    "problem": ("optimize", "problem"),
    "penalties": ("optimize", "penalties"),
    "descent": ("optimize", "descent"),
    "horizon": ("optimize", "horizon"),
    "shooting": ("optimize", "shooting"),
    "adjoint": ("optimize", "adjoint"),
    "sensitivity": ("optimize", "sensitivity"),
    "margins": ("optimize", "margins"),
    "footprint": ("optimize", "footprint"),
    "verify": ("verify", "nominal"),
    "cover": ("verify", "cover"),
    "recertify": ("verify", "recertify"),
    "closed_loop": ("closed_loop", "simulate"),
    "rollouts": ("closed_loop", "rollouts"),
    "gusts": ("closed_loop", "gusts"),
    "worst_case": ("closed_loop", "worst_case"),
    "flight": ("closed_loop", "flight"),
}
SUBMODULES = {
    package: sorted(new for p, new in MOVES.values() if p == package)
    for package, _ in MOVES.values()
}
OLD = "|".join(sorted(MOVES, key=len, reverse=True))
PATH = re.compile(rf"\bpipeline([./])numerics\1({OLD})(?!\w)")
PROSE = re.compile(
    r"(?<![\w./])(funnel_bounds|funnel_check|funnel_law|funnel_lmi|funnel_pieces|"
    r"tube_radius|terminal_fit)(?!\w)(?!\s*[:=])"
)
FROM = re.compile(rf"\bfrom pipeline\.numerics import ({OLD})\b(?! as)(?!,)")


def _path(match: re.Match[str]) -> str:
    sep, old = match.group(1), match.group(2)
    package, new = MOVES[old]
    rest = match.string[match.end() :]
    if old in SUBMODULES and re.match(rf"([./]| import )({'|'.join(SUBMODULES[old])})\b", rest):
        return match.group(0)  # already the package, naming its submodule
    return sep.join(("pipeline", "numerics", package, new))


def _from(match: re.Match[str]) -> str:
    old = match.group(1)
    package, new = MOVES[old]
    alias = "" if new == old else f" as {old}"
    return f"from pipeline.numerics.{package} import {new}{alias}"


def rewrite(text: str) -> str:
    text = FROM.sub(_from, PATH.sub(_path, text))
    return PROSE.sub(lambda m: ".".join(MOVES[m.group(1)]), text)


def main(paths: list[str]) -> None:
    if not paths:
        listed = subprocess.run(["git", "ls-files"], capture_output=True, text=True, check=True)
        paths = [p for p in listed.stdout.split() if p.endswith((".py", ".md", ".toml"))]
    for name in paths:
        path = Path(name)
        if path.resolve() == Path(__file__).resolve() or not path.is_file():
            continue
        text = path.read_text()
        new = rewrite(text)
        if new != text:
            path.write_text(new)
            print(f"rewrote {name}")


if __name__ == "__main__":
    main(sys.argv[1:])
