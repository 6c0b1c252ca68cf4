"""Learning from robot-shaped bags (the robot-bag check): R^2 and timings.

For each camera (bgr8 ``Image``, jpeg ``CompressedImage``, mono8 ``Image``) a bag of the
robot-shaped generator (``sim_node.robot_bag``: 40x40 at 4 Hz with 5-40 ms stamp jitter,
``Twist`` at 2 Hz with +-0.6 m/s jitter, ``/odom``) is fitted with exactly the documented
command (``--step-period 1.0 --image-size 16 --actions 25``, every other parameter at its
default, which for robot bags includes normalised history/test features), and
``learner plot`` prints the R^2 of the true position from the states.
Target: R^2 >= 0.8 in x and y.
"""

from __future__ import annotations

import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

STEPS = 9000
TARGET = 0.8
CAMERA = "/front_camera/image_raw"


def _run(argv: list[str]) -> tuple[float, str]:
    start = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} failed: {done.stderr[-500:]}")
    return time.perf_counter() - start, done.stdout + done.stderr


def main() -> None:
    py = sys.executable
    with tempfile.TemporaryDirectory() as tmp:
        for encoding in ("bgr8", "jpeg", "mono8"):
            bag, model = Path(tmp) / encoding, Path(tmp) / f"{encoding}.npz"
            made, _ = _run([py, "-m", "sim_node.robot_bag", "--steps", str(STEPS),
                            "--encoding", encoding, "-o", str(bag)])
            topic = CAMERA + "/compressed" if encoding == "jpeg" else CAMERA
            fit_s, out = _run([py, "-m", "learner", "fit", str(bag), "--image-topic", topic,
                               "--action-topic", "/cmd_vel", "--pose-topic", "/odom",
                               "--step-period", "1.0", "--image-size", "16", "--actions", "25",
                               "-o", str(model)])
            reading = re.search(r"reading bags ([\d.]+) s", out)
            _, plot = _run([py, "-m", "learner", "plot", str(model), str(bag),
                            "-o", str(Path(tmp) / f"{encoding}.png")])
            r2 = [float(v) for v in re.findall(r"[xy] (-?[\d.]+)", plot.splitlines()[-1])]
            verdict = "ok" if min(r2) >= TARGET else f"below {TARGET}"
            print(f"{encoding:5s}: R^2 x {r2[0]:.3f}, y {r2[1]:.3f} ({verdict}); "
                  f"fit {fit_s:.1f} s (reading {reading.group(1) if reading else '?'} s); "
                  f"bag made in {made:.1f} s ({STEPS} steps)", flush=True)


if __name__ == "__main__":
    main()
