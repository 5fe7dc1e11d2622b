"""Run every ``bench/bench_*.py`` module in name order (``make bench``); ``python -m bench NAME
...`` runs those whose names contain one of the NAMEs. A module that fails is reported with its
traceback and the others still run; the exit code is then 1."""

import importlib
import pkgutil
import sys
import traceback

import bench


def main() -> int:
    names = sorted(
        m.name for m in pkgutil.iter_modules(bench.__path__) if m.name.startswith("bench_")
    )
    only = sys.argv[1:]
    failed = []
    for name in names:
        if only and not any(part in name for part in only):
            continue
        print(f"\n=== {name} ===", flush=True)
        try:
            importlib.import_module(f"bench.{name}").run()
        except Exception:  # one bench's failure must not lose the others' measurements
            traceback.print_exc()
            failed.append(name)
    if failed:
        print(f"\nfailed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


sys.exit(main())
