"""Run every benchmark in bench/ and write one markdown table of what they print.

Run: nice python bench/run_all.py [--out bench/results.md] [--only stabilize,fit] [--timeout 1800]

Each script runs in its own process (one at a time: the machine has 2 cores), with its
default arguments. The table has one row per script: its wall time, exit status and the
lines it printed (its own tables and numbers, kept verbatim so nothing is lost in parsing).
The file is written atomically when every script has finished.
"""

from __future__ import annotations

import argparse
import html
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
SCRIPTS = ["framework_overhead", "synth_performance", "stabilize", "stabilize_head", "detect_faces",
           "landmark_networks", "render_landmarks", "fit", "profile_fit", "temporal", "smoothing", "dynamics", "export", "gpu", "profile_graphs"]


def run_one(name: str, timeout: float) -> tuple[float, str, list[str]]:
    """(seconds, status, printed lines) of one bench script."""
    start = time.perf_counter()
    try:
        proc = subprocess.run([sys.executable, str(HERE / f"{name}.py")], cwd=ROOT, capture_output=True,
                              text=True, timeout=timeout)
        status = "ok" if proc.returncode == 0 else f"exit {proc.returncode}"
        lines = proc.stdout.splitlines()
        if proc.returncode != 0:
            lines += [f"stderr: {line}" for line in proc.stderr.splitlines()[-5:]]
    except subprocess.TimeoutExpired as err:
        status, lines = f"timed out after {timeout:.0f} s", (err.stdout or b"").decode(errors="replace").splitlines()
    return time.perf_counter() - start, status, [line.rstrip() for line in lines if line.strip()]


def markdown(rows: list[tuple[str, float, str, list[str]]]) -> str:
    """One table: script | seconds | status | output (lines joined with <br>, code-formatted)."""
    out = ["| script | seconds | status | output |", "|---|---:|---|---|"]
    for name, seconds, status, lines in rows:
        cells = "<br>".join(f"<code>{html.escape(line).replace('|', '&#124;')}</code>" for line in lines)
        out.append(f"| `bench/{name}.py` | {seconds:.1f} | {status} | {cells} |")
    return "\n".join(out) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(HERE / "results.md"), help="markdown file to write")
    parser.add_argument("--only", default="", help="comma-separated script names (default: all)")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds per script")
    args = parser.parse_args()
    names = [n for n in args.only.split(",") if n] or SCRIPTS
    unknown = sorted(set(names) - set(SCRIPTS))
    if unknown:
        parser.error(f"--only: unknown script(s) {unknown}; known: {SCRIPTS}")
    rows = []
    for name in names:
        print(f"[{len(rows) + 1}/{len(names)}] bench/{name}.py ...", file=sys.stderr, flush=True)
        seconds, status, lines = run_one(name, args.timeout)
        print(f"    {status} in {seconds:.1f} s", file=sys.stderr, flush=True)
        rows.append((name, seconds, status, lines))
    sys.path.insert(0, str(ROOT))
    from nodegraph.files import write_text_atomic

    text = f"# Benchmarks ({time.strftime('%Y-%m-%d %H:%M')}, {sys.platform})\n\n" + markdown(rows)
    write_text_atomic(args.out, text)
    print(text)
    if any(status != "ok" for _, _, status, _ in rows):
        sys.exit(1)


if __name__ == "__main__":
    main()
