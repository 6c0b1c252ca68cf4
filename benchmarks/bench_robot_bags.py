"""Learning from robot-shaped bags with the defaults: R^2 of the true position, and timings.

The table of docs/robot_bags.md ("Measured"): for seeds 0 and 1, bags of
``sim_node.robot_bag`` (``moving``, 9000 steps, bgr8/jpeg/mono8 cameras; ``step-start``,
6000 steps) fitted with only the topics, ``--pose-topic /odom`` and ``--step-period 1.0``
(every other choice sized to the data), and the step-start bag again with ``--step-offset
0`` (steps on the command times, the phase the grid chose before it chose one);
``learner plot`` prints the R^2 of the true position from the states. Target: R^2 >= 0.9.

``--drive``: the turning robot instead (``--environment drive``, ``step-start``, 24000 steps,
the 300 and 90 degree cameras), R^2 of x, y and the heading's cos and sin with the defaults
(targets 0.8 for the 300 degree camera, 0.6 for the 90 degree one) and with the planar
robot's settings.

    python -m benchmarks.bench_robot_bags [--seeds 0 1] [--drive]
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TARGET = 0.9
CAMERA = "/front_camera/image_raw"
CASES = (  # (label, generator options, fit options)
    ("moving, bgr8 `Image`", ["--steps", "9000", "--encoding", "bgr8"], []),
    ("moving, jpeg `CompressedImage`", ["--steps", "9000", "--encoding", "jpeg"], []),
    ("moving, grey (mono8) `Image`", ["--steps", "9000", "--encoding", "mono8"], []),
    ("step-start, bgr8", ["--steps", "6000", "--timeline", "step-start"], []),
    ("step-start, `--step-offset 0`", ["--steps", "6000", "--timeline", "step-start"],
     ["--step-offset", "0"]),
)  # fmt: skip


DRIVE = ["--environment", "drive", "--timeline", "step-start", "--steps", "24000"]
PLANAR_SETTINGS = [
    "--rank", "8", "--ht-dim", "10", "--action-pooling", "1", "--obs-effective-centres", "0",
]  # fmt: skip
DRIVE_CASES = (  # (label, generator options, fit options, target)
    ("drive, 300° camera", [*DRIVE, "--field-of-view", "300"], [], 0.8),
    ("drive, 90° camera", [*DRIVE, "--field-of-view", "90"], [], 0.6),
    ("drive, 300°, the planar settings", [*DRIVE, "--field-of-view", "300"], PLANAR_SETTINGS,
     None),
    ("drive, 90°, the planar settings", [*DRIVE, "--field-of-view", "90"], PLANAR_SETTINGS,
     None),
)  # fmt: skip
_R2 = re.compile(r"(?:^|: |, )(?:x|y|cos heading|sin heading) (-?[\d.]+)")


def _run(argv: list[str]) -> tuple[float, str]:
    start = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} failed: {done.stderr[-500:]}")
    return time.perf_counter() - start, done.stdout + done.stderr


def r2_of(bag: Path, generator: list[str], fit: list[str], seed: int, tmp: Path) -> list[float]:
    """Make the bag (once), fit with the defaults and ``fit``, return the R^2 that ``learner
    plot`` prints (x and y; and the heading's cos and sin for a robot that turns)."""
    py = sys.executable
    if not bag.exists():
        _run([py, "-m", "sim_node.robot_bag", *generator, "--seed", str(seed), "-o", str(bag)])
    topic = CAMERA + "/compressed" if "jpeg" in generator else CAMERA
    model = tmp / "model.npz"
    _run([py, "-m", "learner", "fit", str(bag), "--image-topic", topic, "--action-topic",
          "/cmd_vel", "--pose-topic", "/odom", "--step-period", "1.0", *fit, "-o", str(model),
          "--force"])  # fmt: skip
    _, plot = _run([py, "-m", "learner", "plot", str(model), str(bag), "-o",
                    str(tmp / "states.png"), "--force"])  # fmt: skip
    return [float(v) for v in _R2.findall(plot.splitlines()[-1])]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--drive", action="store_true", help="the turning robot's bags")
    args = parser.parse_args()
    if args.drive:
        _drive(args.seeds)
        return
    print("| bag | " + " | ".join(f"R² x, y (seed {s})" for s in args.seeds) + " |")
    print("|---|" + "---|" * len(args.seeds))
    with tempfile.TemporaryDirectory() as tmp:
        for label, generator, fit in CASES:
            cells = []
            for seed in args.seeds:
                bag = Path(tmp) / f"{'_'.join(generator)}_{seed}".replace("-", "")
                x, y = r2_of(bag, generator, fit, seed, Path(tmp))
                mark = "" if min(x, y) >= TARGET else " (below 0.9)"
                cells.append(f"{x:.3f}, {y:.3f}{mark}")
            print(f"| {label} | " + " | ".join(cells) + " |", flush=True)


def _drive(seeds: list[int]) -> None:
    print("| bag | " + " | ".join(f"R² x, y, cos, sin (seed {s})" for s in seeds) + " |")
    print("|---|" + "---|" * len(seeds))
    with tempfile.TemporaryDirectory() as tmp:
        for label, generator, fit, target in DRIVE_CASES:
            cells = []
            for seed in seeds:
                bag = Path(tmp) / f"drive_{generator[-1]}_{seed}"
                values = r2_of(bag, generator, fit, seed, Path(tmp))
                below = target is not None and min(values) < target
                mark = f" (below {target})" if below else ""
                cells.append(", ".join(f"{v:.3f}" for v in values) + mark)
            print(f"| {label} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
