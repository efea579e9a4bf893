"""Evaluate one MPEM calibration file in ETH's mag_manip (run by the side interpreter that has it).

mag_manip 3.0.0 (PyPI `mag-manip`) needs numpy < 2, so it lives in a virtual environment of its
own (`.ci/run` makes `.venv-mag-manip`); rigctl's bench and integration test run this script
there, one file per process (mag_manip drops the Offset of every model loaded after the first in a
process). Reads a JSON request on stdin, {"points_m": [[x, y, z], ...], "currents_A": [[...],
...], "repeat": n}, and prints one JSON object: per point and current vector the field and five
gradient terms (`computeFieldGradient5FromCurrents`), per point the 8 x N actuation matrix
(`getActuationMatrix`), and the best time per evaluation in microseconds over `repeat` calls.
"""

import json
import os
import sys
import time

import numpy as np
from mag_manip import mag_manip


def main() -> None:
    path = sys.argv[1]
    request = json.loads(sys.argv[2]) if len(sys.argv) > 2 else json.load(sys.stdin)
    model = mag_manip.ForwardModelMPEM()
    model.setCalibrationFile(path)
    points = np.asarray(request["points_m"], dtype=float)
    currents = np.asarray(request["currents_A"], dtype=float)
    # mag_manip 3.0.0 sometimes loads a file's Offset as nothing, even the first file of a process
    # (seen in about one process in three, depending on nothing we pass it: the same file and
    # request on a pipe or from a file); a process that lost it starts again, up to 10 times
    zero = model.computeFieldGradient5FromCurrents(points[0], np.zeros(model.getNumCoils()))
    tries = int(os.environ.get("MAG_MANIP_EVAL_TRY", "1"))
    if "Offset" in open(path).read() and not np.any(zero) and tries < 10:
        os.environ["MAG_MANIP_EVAL_TRY"] = str(tries + 1)
        os.execv(sys.executable, [sys.executable, *sys.argv, json.dumps(request)])
    fg = [[model.computeFieldGradient5FromCurrents(p, i).ravel().tolist() for i in currents]
          for p in points]
    actuation = [np.asarray(model.getActuationMatrix(p)).tolist() for p in points]
    repeat = int(request.get("repeat", 0))
    best = None
    for _ in range(repeat):
        started = time.perf_counter()
        model.computeFieldGradient5FromCurrents(points[0], currents[0])
        elapsed = time.perf_counter() - started
        best = elapsed if best is None else min(best, elapsed)
    print(json.dumps({"field_gradient5": fg, "actuation": actuation, "coils": model.getNumCoils(),
                      "eval_us": None if best is None else best * 1e6}))


if __name__ == "__main__":
    main()
