"""A stand-in for the recipe in ``launch_grid``'s stop tests: it records every stop signal
it gets, says when it is ready, and after the first signal takes a second, as a run
finishing its batch and checkpointing does, before it writes them down and exits."""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path


def main() -> None:
    run_dir = Path(next(a.split("=", 1)[1] for a in sys.argv[1:] if a.startswith("hydra.run.dir=")))
    received: list[int] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: received.append(signum))
    (run_dir / "started").write_text(f"{os.getpid()} {os.getsid(0)}")
    while not received:
        time.sleep(0.02)
    time.sleep(1.0)
    (run_dir / "signals").write_text(" ".join(str(s) for s in received))


if __name__ == "__main__":  # pytest imports this file when it collects tests/
    main()
