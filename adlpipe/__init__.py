"""adlpipe: ADL robot-manipulation bags -> HDF5 -> flow-matching / diffusion / BC policies -> evaluation."""

import os
import signal
import sys

__version__ = "0.1.0"


def _interrupted_while_starting(_signum: int, _frame: object) -> None:
    print("adlpipe: interrupted while starting; no output was replaced", file=sys.stderr)
    os._exit(130)


if sys.argv[:1] == ["-m"] or os.path.basename(sys.argv[0] if sys.argv else "") == "adlpipe":
    # Started as `python -m adlpipe.<stage>` or as the `adlpipe` console command: a Ctrl-C while torch, cv2 and
    # mujoco import is a clean exit 130, not a traceback. The stage's run_cli puts Python's KeyboardInterrupt
    # handling back once the imports are done.
    signal.signal(signal.SIGINT, _interrupted_while_starting)
