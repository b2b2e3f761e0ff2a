"""Ctrl-C stress on the kernels with a wall-clock judge: children of test_native's
_INTERRUPT_CHILD (loops over the native kernels on 2 threads), SIGINTs at random moments,
``--children`` at a time for ``--seconds``, plus one process spinning on a core. A child is
"hung" when it gives no line within 30 s of a SIGINT or does not exit within 30 s of its
last one (the test's rule until 2026-11-28); then the stacks of all its threads (gdb, where
installed) go to ``--out`` with its per-thread CPU times 5 s apart (busy or asleep).

    nice -n 19 python scripts/tools/ctrl_c_stress.py --seconds 150 --out /tmp/ctrl_c \\
        [--root OTHER_CHECKOUT]

(with one busy loop at normal priority beside it, this reproduced the "hangs" of
2026-11-28: children starved of CPU, busy in the interpreter's shutdown; see CHANGELOG).
"""

from __future__ import annotations

import argparse
import os
import queue
import random
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _thread_cpu(pid: int) -> dict[str, tuple[str, int]]:
    """Per thread: (state, CPU ticks)."""
    out = {}
    for t in os.listdir(f"/proc/{pid}/task"):
        try:
            f = Path(f"/proc/{pid}/task/{t}/stat").read_text().rsplit(")", 1)[1].split()
            out[t] = (f[0], int(f[11]) + int(f[12]))
        except OSError:
            pass
    return out


def _stacks(pid: int) -> str:
    if not shutil.which("gdb"):
        return "(no gdb)"
    return subprocess.run(["gdb", "-p", str(pid), "-batch", "-ex", "thread apply all bt 30"],
                          capture_output=True, text=True, timeout=120).stdout


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=150.0)
    ap.add_argument("--children", type=int, default=2)
    ap.add_argument("--interrupts", type=int, default=4)
    ap.add_argument("--seed", type=int, default=13)
    ap.add_argument("--root", type=Path, default=ROOT, help="the checkout to test")
    ap.add_argument("--out", type=Path, default=Path("ctrl_c_stress"))
    a = ap.parse_args()
    sys.path[:0] = [str(a.root / "tests"), str(a.root)]
    import test_native

    a.out.mkdir(parents=True, exist_ok=True)
    script = a.out / "child.py"
    script.write_text(test_native._INTERRUPT_CHILD)
    env = {**os.environ, "PYTHONPATH": str(a.root), "MALLOC_MMAP_THRESHOLD_": "65536"}
    stats = {"children": 0, "sigints": 0, "problems": 0}
    lock = threading.Lock()
    rng = random.Random(a.seed)

    def drive(k: int) -> None:
        ch = subprocess.Popen([sys.executable, str(script), str(a.interrupts)], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        lines: queue.Queue = queue.Queue()
        threading.Thread(target=lambda: [lines.put(x.strip()) for x in ch.stdout],
                         daemon=True).start()

        def line(timeout: float) -> str | None:
            try:
                return lines.get(timeout=timeout)
            except queue.Empty:
                return None

        got: list[str | None] = []
        if line(120) == "ready":
            for _ in range(a.interrupts):
                with lock:
                    delay = rng.uniform(0.02, 0.4)
                time.sleep(delay)
                ch.send_signal(signal.SIGINT)
                got.append(line(30))
                if got[-1] is None or not got[-1].endswith(("ok", "exit")):
                    break
        if got and got[-1] is None and ch.poll() is None:
            s0 = _thread_cpu(ch.pid)
            time.sleep(5)
            s1 = _thread_cpu(ch.pid)
            (a.out / f"silent-{a.seed}-{k}.txt").write_text(f"{s0}\n{s1}\n{_stacks(ch.pid)}")
        try:
            rc: int | str = ch.wait(timeout=30)
        except subprocess.TimeoutExpired:
            s0 = _thread_cpu(ch.pid)
            time.sleep(5)
            s1 = _thread_cpu(ch.pid)
            (a.out / f"no-exit-{a.seed}-{k}.txt").write_text(f"{s0}\n{s1}\n{_stacks(ch.pid)}")
            ch.kill()
            ch.wait()
            rc = "hung"
        err = ch.stderr.read()
        bad = rc != 130 or got[-1:] != [f"interrupted {a.interrupts} exit"] or \
            any(not (x or "").endswith(("ok", "exit")) for x in got) or \
            "Exception ignored" in err or "Traceback" in err
        with lock:
            stats["children"] += 1
            stats["sigints"] += len(got)
            if bad:
                stats["problems"] += 1
                print(f"problem: child {k}: exit {rc}, lines {got}, stderr {err[-300:]!r}",
                      flush=True)

    t_end = time.monotonic() + a.seconds
    k = 0
    burner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        while time.monotonic() < t_end:
            drivers = [threading.Thread(target=drive, args=(k + j,))
                       for j in range(a.children)]
            k += a.children
            for d in drivers:
                d.start()
            for d in drivers:
                d.join()
            print(stats, flush=True)
    finally:
        burner.kill()
        burner.wait()
    print("final", stats, flush=True)
    return 1 if stats["problems"] else 0


if __name__ == "__main__":
    sys.exit(main())
