"""A virtual camera photographing a glass scene through the polarizer on the stage.

It renders the paper's image formation model (`separate.optics.render`) from two natural
images (reflection and transmission at the glass), an angle-of-incidence map of a flat or
gently curved pane seen from a finite distance, and an s-direction map. The polarizer angle
comes from the stage at trigger time (so mounting offset and jitter show in the pixels). Each
shot after the first is shaken by a random translation and rotation; the sensor adds shot
and read noise and writes a real Bayer DNG. Ground truth (the observable layers in decoded
units, θ and φ⊥ maps) is written by `write_truth`; each DNG's ImageDescription carries its
shot index, true polarizer angle and shake as JSON.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import tifffile

from acquire.camera import CameraKind
from acquire.dng import write_dng
from separate import optics
from separate.optics import parabola_aoi, photo_to_linear
from urd.core import raw as rawio
from urd.core.truth import TRUTH_FILE, write_truth_record
from urd.core.files import atomic_path


@dataclasses.dataclass
class GlassScene:
    """Radiance at the glass and its geometry; arrays H×W(×3), float32, linear; angles rad."""

    reflection: np.ndarray
    transmission: np.ndarray
    theta: np.ndarray
    phi_perp: np.ndarray
    n: float = optics.N_GLASS

    @property
    def shape(self) -> tuple[int, int]:
        return self.theta.shape

    def render(self, phi: float) -> np.ndarray:
        """Linear H×W×3 image behind a polarizer at ``phi`` (rad), paper Eq. 1."""
        return optics.render(self.reflection, self.transmission, self.theta, self.phi_perp, phi, self.n)

    def layers(self) -> tuple[np.ndarray, np.ndarray]:
        """The observable layers (R_obs, T_obs), H×W×3."""
        return optics.observable_layers(self.reflection, self.transmission, self.theta, self.n)


@dataclasses.dataclass
class PolarizedTarget:
    """A calibration target: an image whose light is linearly polarized at ``angle`` (rad)
    with degree ``dolp`` (e.g. a sheet polarizer in front of a light box or an LCD)."""

    image: np.ndarray
    angle: float
    dolp: float = 0.95

    @property
    def shape(self) -> tuple[int, int]:
        return self.image.shape[:2]

    def render(self, phi: float) -> np.ndarray:
        return optics.intensity_from_stokes(optics.stokes_from_polarization(self.image, self.dolp, self.angle), phi)

    def layers(self) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros_like(self.image), self.image


def make_polarized_target(width: int, height: int, angle_deg: float = 0.0) -> PolarizedTarget:
    """A bundled photo seen through a sheet polarizer whose axis is at ``angle_deg``."""
    import skimage.data

    return PolarizedTarget(photo_to_linear(_cover(skimage.data.chelsea(), width, height)) * 0.8 + 0.05, np.radians(angle_deg))


def _cover(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Scale and centre-crop an image to exactly width×height."""
    scale = max(width / img.shape[1], height / img.shape[0])
    resized = cv2.resize(img, (max(width, round(img.shape[1] * scale)), max(height, round(img.shape[0] * scale))), interpolation=cv2.INTER_CUBIC)
    y, x = (resized.shape[0] - height) // 2, (resized.shape[1] - width) // 2
    return resized[y : y + height, x : x + width]


def make_glass_scene(width: int = 1536, height: int = 1024, reflection: Path | None = None,
                     transmission: Path | None = None, curved: bool = True,
                     theta_center_deg: float = 50.0, phi_perp_deg: float = 90.0) -> GlassScene:
    """A window scene: the reflection brighter than the transmission, θ across the pane.

    The pane's s-direction is ``phi_perp_deg`` at the centre (turning by 6° from top to bottom)
    and θ changes along the plane of incidence, the image direction φ⊥ − 90° (the default: a
    window seen from one side, θ growing across the columns, s vertical), as on a real pane
    (`separate.synthesis.surface_maps` likewise). Defaults use scikit-image's bundled photos
    (astronaut reflected, coffee transmitted); ``reflection`` and ``transmission`` take any
    image files instead.
    """
    if width % 2 or height % 2 or width < 32 or height < 32:
        raise ValueError(f"expected an even sensor size of at least 32×32, got {width}×{height}")
    import skimage.data

    refl_u8 = _read_rgb(reflection) if reflection else skimage.data.astronaut()
    trans_u8 = _read_rgb(transmission) if transmission else skimage.data.coffee()
    refl = photo_to_linear(_cover(refl_u8, width, height)) * 1.6
    trans = photo_to_linear(_cover(trans_u8, width, height)) * 0.9
    omega = np.radians(phi_perp_deg) - np.pi / 2                       # the plane of incidence's image direction
    xs = np.linspace(-0.5, 0.5, width, dtype=np.float32)[None, :]
    ys = np.linspace(-0.5, 0.5, height, dtype=np.float32)[:, None] * (height / width)     # square pixels
    along = xs * np.float32(np.cos(omega)) - ys * np.float32(np.sin(omega))               # rows grow downwards, angles count upwards
    profile = np.linspace(float(along.min()), float(along.max()), 4096)         # θ is smooth along it: interpolated
    theta = np.interp(along, profile, parabola_aoi(np.radians(theta_center_deg), 2.0, 1.5, 0.03 if curved else 0.0, 1, profile))
    theta = theta.astype(np.float32)
    ys = np.linspace(-0.5, 0.5, height)[:, None]
    phi_perp = np.broadcast_to(np.radians(phi_perp_deg + 6.0 * ys), (height, width)).astype(np.float32)
    return GlassScene(refl.astype(np.float32), trans.astype(np.float32), theta, np.ascontiguousarray(phi_perp))


def _read_rgb(path: Path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError(f"cannot read image {path}")
    return np.ascontiguousarray(bgr[..., ::-1])


class VirtualCamera:
    """Simulated camera with a Bayer sensor; same `capture` API as the real drivers.

    Args:
        scene: what is in front of the camera (a `GlassScene` or a `PolarizedTarget`).
        angle_source: returns the polarizer's true angle (deg) when the shutter fires.
        shake_px, shake_deg: maximum random translation (px) and rotation (deg) of shots ≥ 1.
        exposure: mean linear level of the unpolarized image (1.0 = white level).
        full_well: electrons at white level (sets shot noise).
        read_noise_dn: read noise standard deviation (DN).
        seed: seed of shake and noise (per shot index, so a resumed capture repeats them).
    """

    black_level = 256
    white_level = 4095
    neutral = (0.5, 1.0, 0.7)

    def __init__(self, scene: GlassScene | PolarizedTarget, angle_source: Callable[[], float], shake_px: float = 4.0,
                 shake_deg: float = 0.5, exposure: float = 0.3, full_well: float = 20000.0,
                 read_noise_dn: float = 1.5, seed: int = 0):
        self.scene = scene
        self.angle_source = angle_source
        self.shake_px, self.shake_deg = shake_px, shake_deg
        self.full_well, self.read_noise_dn = full_well, read_noise_dn
        self.seed = seed
        r_obs, t_obs = scene.layers()
        self.gain = exposure / float((r_obs + t_obs).mean())
        self.triggers: list[dict] = []

    def describe(self) -> dict:
        h, w = self.scene.shape
        return {"kind": CameraKind.VIRTUAL.value, "model": "urd virtual camera", "width": w, "height": h,
                "shake_px": self.shake_px, "shake_deg": self.shake_deg, "seed": self.seed}

    def _shake_draw(self, index: int) -> tuple[float, float, float]:
        """Shot ``index``'s translation (px) and turn (deg, counter-clockwise: the scene turns so in
        the shot, the camera the other way); zero for shot 0."""
        if index == 0:
            return 0.0, 0.0, 0.0
        rng = np.random.default_rng([self.seed, index, 1])
        tx, ty = rng.uniform(-self.shake_px, self.shake_px, 2)
        return float(tx), float(ty), float(rng.uniform(-self.shake_deg, self.shake_deg))

    def shake(self, index: int) -> np.ndarray:
        """The 2×3 affine warp M of shot ``index``: shot(M·x) = scene(x); identity for shot 0."""
        h, w = self.scene.shape
        tx, ty, turn = self._shake_draw(index)
        m = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), turn, 1.0)
        m[:, 2] += (tx, ty)
        return m.astype(np.float32)

    def scene_angle_deg(self, angle_deg: float, index: int) -> float:
        """The polarizer's angle in the scene's frame (the reference shot's, deg) when it stands at
        ``angle_deg`` in the camera's: the polarizer sits in front of the lens and turns with the
        camera, against the scene's turn in the shot (`shake`)."""
        return angle_deg - self._shake_draw(index)[2]

    def render(self, angle_deg: float, index: int) -> np.ndarray:
        """The noiseless linear image of shot ``index`` with the polarizer at ``angle_deg`` in the
        camera's frame (`scene_angle_deg` in the scene's)."""
        img = self.scene.render(np.radians(self.scene_angle_deg(angle_deg, index))) * self.gain
        h, w = self.scene.shape
        return cv2.warpAffine(img.astype(np.float32), self.shake(index), (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)

    def mosaic(self, img: np.ndarray, index: int) -> np.ndarray:
        """Linear RGB → noisy RGGB mosaic in DN (uint16)."""
        h, w = img.shape[:2]
        signal = np.empty((h, w), np.float32)
        signal[0::2, 0::2] = img[0::2, 0::2, 0] * self.neutral[0]
        signal[0::2, 1::2] = img[0::2, 1::2, 1]
        signal[1::2, 0::2] = img[1::2, 0::2, 1]
        signal[1::2, 1::2] = img[1::2, 1::2, 2] * self.neutral[2]
        rng = np.random.default_rng([self.seed, index, 2])
        electrons = np.clip(signal, 0, None) * self.full_well
        electrons += rng.standard_normal((h, w), np.float32) * np.sqrt(electrons)
        dn = self.black_level + electrons * ((self.white_level - self.black_level) / self.full_well)
        dn += rng.standard_normal((h, w), np.float32) * self.read_noise_dn
        return np.clip(np.rint(dn), 0, self.white_level).astype(np.uint16)

    def capture(self, folder: Path, index: int) -> tuple[Path, dict]:
        angle = float(self.angle_source())
        m = self.shake(index)
        info = {"shot": index, "true_angle_deg": angle, "scene_angle_deg": self.scene_angle_deg(angle, index),
                "shake_matrix": m.tolist(), "seed": self.seed}
        cfa = self.mosaic(self.render(angle, index), index)
        fd, name = tempfile.mkstemp(dir=folder, prefix=".shot-", suffix=".dng")
        os.close(fd)
        try:
            write_dng(Path(name), cfa, self.black_level, self.white_level, self.neutral,
                      description=json.dumps({"urd_virtual": info}))
        except BaseException:
            Path(name).unlink(missing_ok=True)
            raise
        self.triggers.append(info)
        return Path(name), rawio.metadata(Path(name))

    def write_truth(self, folder: Path) -> None:
        """Write the ground truth in decoded units: R_obs.tiff, T_obs.tiff (float32 H×W×3),
        for glass scenes theta_deg.tiff and phi_perp_deg.tiff (float32 H×W), each atomically,
        then truth.json (gain, camera, and each file's size and SHA-256,
        `urd.core.truth.write_truth_record`): its presence marks the folder complete, and
        ``urd verify`` checks the files against it. Existing files are replaced."""
        folder.mkdir(parents=True, exist_ok=True)
        s = self.scene
        r_obs, t_obs = s.layers()
        arrays = [("R_obs", r_obs * self.gain), ("T_obs", t_obs * self.gain)]
        if isinstance(s, GlassScene):
            arrays += [("theta_deg", np.degrees(s.theta)), ("phi_perp_deg", np.degrees(s.phi_perp))]
        (folder / TRUTH_FILE).unlink(missing_ok=True)              # incomplete until rewritten
        for name, array in arrays:
            array = np.asarray(array, np.float32)
            with atomic_path(folder / f"{name}.tiff", overwrite=True) as tmp:
                tifffile.imwrite(tmp, array, photometric="rgb" if array.ndim == 3 else "minisblack")
        write_truth_record(folder, {"gain": self.gain, "camera": self.describe()})


def shot_truth(path: Path) -> dict | None:
    """The virtual camera's record embedded in a DNG (None for other files)."""
    text = rawio.description(path)
    if not text.startswith("{"):
        return None
    return json.loads(text).get("urd_virtual")
