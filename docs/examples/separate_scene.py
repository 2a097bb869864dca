"""Separate one scene of an urd dataset from Python, compare two methods and save the maps.

    urd demo                                              # a simulated dataset with one scene: urd-demo/
    python docs/examples/separate_scene.py urd-demo scene_01 maps/
"""

import sys
from pathlib import Path

import numpy as np
import tifffile

import urd

root, name, out = sys.argv[1], sys.argv[2], Path(sys.argv[3])
dataset = urd.open_dataset(root)
images, angles_deg = dataset.scene(name).load_stack()        # (N, H, W, 3) float32 linear, angles in degrees
print(f"{name}: {images.shape[0]} shots of {images.shape[2]}x{images.shape[1]} at {angles_deg} deg")

network = urd.separate(images, angles_deg)                     # the shipped network, reference estimated per pixel
classical = urd.separate(images, angles_deg, method="schechner", reference="global")
for label, layers in (("network", network), ("schechner", classical)):
    share = layers.reflection.sum() / (layers.reflection.sum() + layers.transmission.sum())
    print(f"{label:9s}: reflection holds {100 * share:.1f}% of the light")

maps = urd.polarization_maps(images, angles_deg)
out.mkdir(parents=True, exist_ok=True)
for key in ("DoLP", "AoLP", "phi_perp"):
    tifffile.imwrite(out / f"{key}.tiff", maps[key])
theta = maps["theta"]                                          # per pixel: the angle of incidence turns across a wide view
print(f"DoLP median {np.nanmedian(maps['DoLP']):.3f} (NaN: dark pixels); "
      f"phi_perp {maps['phi_perp'].min():.1f} to {maps['phi_perp'].max():.1f} deg; "
      f"angle of incidence {np.median(theta):.1f} deg ({theta.min():.1f} to {theta.max():.1f} across the frame); maps in {out}")
