"""Start-up cost of the ``vtr`` command: median wall time of fresh processes.

usage: python tools/bench_startup.py [--repeats 5] [--clip datasets/kitti06_clip] [--tty]

Measures, each in ``--repeats`` fresh processes (median, min and max printed):
  - ``vtr --help``                 (goal: <= 0.4 s; a help page imports no numerical library)
  - ``vtr versions``               (imports every heavy dependency on purpose)
  - ``vtr odometry CLIP --out TMP``: time from the process start to the first processed frame, read from
    the progress output on stderr (``odometry: 1/51 frames``, the line progress printed when stderr is not
    a terminal), and the whole run.
``--tty`` runs odometry under a pseudo-terminal and takes the first tqdm bar update with at least one frame
done instead (for versions of vtr that printed no line progress; tqdm may skip frame 1, so it can read late).

The processes run as a user runs them: ``python -m vtr`` with the caller's environment (set PYTHONPATH to
the checkout to time). The numba kernels are compiled once before timing (their on-disk cache is warm).
"""

from __future__ import annotations

import argparse
import os
import re
import select
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIRST_FRAME = re.compile(rb"\b([1-9]\d*)/\d+")


def vtr_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "vtr", *args]


def wall(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True)
    if r.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{r.stderr.decode(errors='replace')}")
    return time.perf_counter() - t0


def first_frame(cmd: list[str], tty: bool) -> tuple[float, float]:
    """(seconds to the first processed frame, seconds to the end) of one odometry process."""
    if tty:
        import fcntl
        import pty
        import struct
        import termios

        master, slave = pty.openpty()
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 160, 0, 0))  # a 160-column terminal
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=slave)
        os.close(slave)
        fd = master
    else:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        assert proc.stderr is not None
        fd = proc.stderr.fileno()
    seen, t_first = b"", float("nan")
    while True:
        ready, _, _ = select.select([fd], [], [], 1.0)
        if not ready:
            if proc.poll() is not None:
                break
            continue
        try:
            chunk = os.read(fd, 4096)
        except OSError:  # pty closed by the child
            chunk = b""
        if not chunk:
            break
        seen += chunk
        if t_first != t_first and FIRST_FRAME.search(seen):
            t_first = time.perf_counter() - t0
    rc = proc.wait()
    t_end = time.perf_counter() - t0
    if tty:
        os.close(master)
    if rc != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{seen.decode(errors='replace')}")
    return t_first, t_end


def summary(name: str, values: list[float]) -> str:
    return (
        f"{name:<42s} median {statistics.median(values):6.3f} s  "
        f"(min {min(values):.3f}, max {max(values):.3f}, n {len(values)})"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--clip", type=Path, default=ROOT / "datasets" / "kitti06_clip")
    ap.add_argument("--tty", action="store_true", help="read odometry progress through a pseudo-terminal")
    args = ap.parse_args()

    subprocess.run([sys.executable, "-m", "vtr.vo.kernels"], check=True, capture_output=True)  # warm cache
    wall(vtr_cmd("--help"))  # warm page cache
    helps = [wall(vtr_cmd("--help")) for _ in range(args.repeats)]
    versions = [wall(vtr_cmd("versions")) for _ in range(args.repeats)]
    firsts, ends = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.repeats):
            out = Path(tmp) / f"odo{i}"
            t_first, t_end = first_frame(vtr_cmd("odometry", str(args.clip), "--out", str(out)), args.tty)
            firsts.append(t_first)
            ends.append(t_end)
    print(
        f"python {sys.version.split()[0]}, {os.cpu_count()} cores, vtr from {Path(__import__('vtr').__file__).parent}"
    )
    print(
        summary("vtr --help", helps)
        + ("   goal <= 0.4 s" if statistics.median(helps) <= 0.4 else "   ABOVE the 0.4 s goal")
    )
    print(summary("vtr versions", versions))
    print(summary(f"vtr odometry {args.clip.name}: first frame", firsts))
    print(summary(f"vtr odometry {args.clip.name}: whole run", ends))


if __name__ == "__main__":
    main()
