"""Time every separation method on a 1-megapixel simulated-rig scene (1224×816), printed.

    python tools/bench_baselines.py
"""

import shutil
import subprocess
import sys
import time

from separate.methods import METHODS, get_method
from urd.core.dataset import Dataset

folder = "/tmp/urd-bench-1mp"
shutil.rmtree(folder, ignore_errors=True)
for step in (["capture", folder, "--stage", "sim", "--camera", "virtual", "--sim-size", "1224x816"],
             ["ingest", f"{folder}/scene_01"]):
    subprocess.run([sys.executable, "-m", "urd.cli", *step], check=True, capture_output=True)
stack, angles = Dataset.open(folder).scene("scene_01").load_stack()
print(f"1-megapixel scene {stack.shape[2]}x{stack.shape[1]}, {len(angles)} shots")
for name in METHODS:
    run, _ = get_method(name)
    started = time.perf_counter()
    run(stack, angles)
    print(f"{name:16s} {time.perf_counter() - started:7.1f} s")
