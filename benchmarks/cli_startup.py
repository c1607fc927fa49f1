"""Benchmark the command line's start: ``mocaprig --help`` against a bare Python and torch.

Every ``mocaprig`` command first builds the parser, which imports every command module
(``mocaprig.commands`` entry points); the packages behind them import their public names on
first use (:mod:`mocaprig.lazy_exports`), so that building it does not import torch. Runs each
command ``--rounds`` times, interleaved, in fresh processes and prints the medians and their
ratios to a bare ``python -c pass``; the last line is one JSON object (``help_s``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any


def _commands() -> dict[str, list[str]]:
    exe = shutil.which("mocaprig", path=str(Path(sys.executable).parent)) or "mocaprig"
    py = sys.executable
    return {
        "python": [py, "-c", "pass"],
        "parser": [py, "-c", "from mocaprig.cli import _build_parser; _build_parser()"],
        "help": [exe, "--help"],
        "import_torch": [py, "-c", "import torch"],
        "parser_imports_torch": [
            py,
            "-c",
            (
                "import sys; from mocaprig.cli import _build_parser; _build_parser(); "
                "sys.exit(int('torch' in sys.modules))"
            ),
        ],
    }


def _wall_s(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=7, help="runs of each command (default 7)")
    args = ap.parse_args(argv)
    cmds = _commands()
    times: dict[str, list[float]] = {k: [] for k in cmds if k != "parser_imports_torch"}
    for _ in range(args.rounds):
        for name in times:
            times[name].append(_wall_s(cmds[name]))
    torch_free = subprocess.run(cmds["parser_imports_torch"], check=False).returncode == 0
    med = {k: statistics.median(v) for k, v in times.items()}
    out: dict[str, Any] = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, "
        f"Python {platform.python_version()}",
        "rounds": args.rounds,
        **{f"{k}_s": round(v, 3) for k, v in med.items()},
        "help_over_python": round(med["help"] / med["python"], 1),
        "import_torch_over_help": round(med["import_torch"] / med["help"], 2),
        "parser_without_torch": torch_free,
    }
    for k, v in med.items():
        print(f"{k:>13}: median {v:.3f} s over {args.rounds} runs")
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
