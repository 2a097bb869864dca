"""ECC alignment of the sequential shots of a scene to its first shot.

Representation: the shots differ not only by camera shake but by the polarizer, which scales
the reflection (and a little the transmission) differently in each shot. ECC maximizes a
zero-mean normalized correlation, which is invariant to one global gain and offset but not to
such local, multiplicative changes. urd therefore aligns band-passed log-luminance: the log
turns a layer's gain change into an additive offset, and subtracting a wide Gaussian blur
removes that offset locally, leaving the edges of both layers, which move together with the
camera. Pixels clipped in any colour channel, in the reference or in the shot, are masked in
each (`findTransformECCWithMask`): a glint that saturates one shot and not the other is no edge
the two share.

Coarse-to-fine: phase correlation gives a starting translation on the coarsest level (about
256 px on the short side); ECC then refines on each pyramid level up to ``finest_level`` (0 is
full resolution), each level starting from the previous warp.
"""

from __future__ import annotations

import dataclasses
import enum

import cv2
import numpy as np

from urd.core.errors import AlignmentError


class Motion(enum.Enum):
    """Alignment models (OpenCV's motion types)."""

    TRANSLATION = "translation"
    EUCLIDEAN = "euclidean"
    HOMOGRAPHY = "homography"

    @property
    def cv_type(self) -> int:
        return {"translation": cv2.MOTION_TRANSLATION, "euclidean": cv2.MOTION_EUCLIDEAN,
                "homography": cv2.MOTION_HOMOGRAPHY}[self.value]


@dataclasses.dataclass
class Alignment:
    """Warp of one shot onto the reference: shot(W·x) ≈ reference(x), x in pixels."""

    warp: np.ndarray
    correlation: float
    ok: bool
    reason: str = ""

    @property
    def turn_deg(self) -> float:
        """The shot's turn against the reference (deg, counter-clockwise in urd's convention):
        atan2(W₁₀, W₀₀) of the warp (pixels, rows downwards)."""
        return float(np.degrees(np.arctan2(self.warp[1, 0], self.warp[0, 0])))

    def record(self) -> dict:
        """The manifest's record; an accepted warp carries its turn (`turn_deg`), which the polarizer
        in front of the lens shares (`urd.core.shots.SceneShots.frame_turns_deg`)."""
        return {"warp": np.round(self.warp, 6).tolist(), "ecc_correlation": round(self.correlation, 4),
                "ok": self.ok, "reason": self.reason, **({"turn_deg": round(self.turn_deg, 4)} if self.ok else {})}


def representation(lum: np.ndarray, clipped: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Band-passed log-luminance (float32 H×W) of ``lum`` (H×W luminance) and a mask (uint8) of
    the pixels neither ``clipped`` (H×W bool, `clipped_pixels`) nor next to one, away from the
    border (2% of the long side), where a shaken shot has no valid content."""
    log = np.log(np.maximum(lum, 1e-4)).astype(np.float32)
    band = log - cv2.GaussianBlur(log, (0, 0), max(4.0, min(lum.shape) / 64))
    mask = cv2.erode((~clipped).astype(np.uint8), np.ones((3, 3), np.uint8))
    margin = max(2, int(0.02 * max(lum.shape)))
    mask[:margin], mask[-margin:], mask[:, :margin], mask[:, -margin:] = 0, 0, 0, 0
    return band, mask


def clipped_pixels(image: np.ndarray, level: int, saturation: float = 0.98) -> np.ndarray:
    """Where ``image`` (H×W×C or H×W, linear, full resolution) reaches ``saturation`` in any
    channel, on the grid of its pyramid ``level`` (`_reduce`): a cell is clipped when any pixel
    under it is. Bool, ⌈H/2^level⌉×⌈W/2^level⌉."""
    h, w = image.shape[:2]
    brightest = cv2.reduce(image.reshape(h * w, -1), 1, cv2.REDUCE_MAX).reshape(h, w) if image.ndim == 3 else image
    clipped = brightest >= saturation
    for _ in range(level):
        rows, cols = clipped.shape
        clipped = np.pad(clipped, ((0, rows % 2), (0, cols % 2)), mode="edge")
        clipped = clipped[0::2, 0::2] | clipped[1::2, 0::2] | clipped[0::2, 1::2] | clipped[1::2, 1::2]
    return clipped


def _scale_warp(warp: np.ndarray, factor: float) -> np.ndarray:
    """Express a warp estimated at one pyramid level at a level ``factor`` times larger."""
    out = warp.copy()
    if out.shape[0] == 2:
        out[:, 2] *= factor
    else:
        out[:2, 2] *= factor
        out[2, :2] /= factor
    return out


def finest_level_for(shape: tuple[int, ...], max_pixels: float = 8e6) -> int:
    """The finest pyramid level with at most ``max_pixels`` (0 up to 8 MP, 1 for 24 MP)."""
    level = 0
    while shape[0] * shape[1] / 4**level > max_pixels:
        level += 1
    return level


def luminance(image: np.ndarray) -> np.ndarray:
    """The mean of an H×W×C image's channels (H×W; an H×W image as it is): for float32, the
    channels added in turn, the very values of ``image.mean(axis=2)`` in a third of its time."""
    if image.ndim == 2:
        return image
    if image.dtype != np.float32:
        return image.mean(axis=2)
    lum = image[..., 0].copy()
    for c in range(1, image.shape[2]):
        lum += image[..., c]
    lum /= np.float32(image.shape[2])
    return lum


def _reduce(image: np.ndarray, level: int) -> np.ndarray:
    """Luminance (float32) reduced by 2**level with a Gaussian pyramid."""
    lum = luminance(image).astype(np.float32, copy=False)
    for _ in range(level):
        lum = cv2.pyrDown(lum)
    return lum


@dataclasses.dataclass(frozen=True)
class Target:
    """A reference shot prepared once for `align`ing every other shot to it: its shape, the
    finest pyramid level refined, and its representation and mask (`representation`) on each
    level from that one to the coarsest (about 256 px on the short side)."""

    shape: tuple[int, ...]
    finest_level: int
    pyramid: list[tuple[np.ndarray, np.ndarray]]


def prepare_target(reference: np.ndarray, finest_level: int | None = None) -> Target:
    """The `Target` of ``reference`` (H×W×C linear float32); ``finest_level`` as in `align`."""
    if finest_level is None:
        finest_level = finest_level_for(reference.shape)
    levels = max(finest_level, int(np.floor(np.log2(min(reference.shape[:2]) / 256))))
    return Target(tuple(reference.shape), finest_level, _pyramid(reference, finest_level, levels - finest_level))


def _pyramid(image: np.ndarray, finest_level: int, coarser: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """`representation` and mask of ``image`` on its pyramid ``finest_level`` and the ``coarser``
    levels above it."""
    pyramid = [representation(_reduce(image, finest_level), clipped_pixels(image, finest_level))]
    for _ in range(coarser):
        rep, mask = pyramid[-1]
        size = ((rep.shape[1] + 1) // 2, (rep.shape[0] + 1) // 2)
        pyramid.append((cv2.pyrDown(rep), cv2.resize(mask, size, interpolation=cv2.INTER_NEAREST)))
    return pyramid


def align(reference: np.ndarray | Target, shot: np.ndarray, motion: Motion = Motion.EUCLIDEAN,
          finest_level: int | None = None, min_correlation: float = 0.6, max_shift_frac: float = 0.05,
          max_rotation_deg: float = 5.0) -> Alignment:
    """Estimate the warp of ``shot`` onto ``reference`` (both H×W×C linear float32; the
    reference may be prepared once for several shots, `prepare_target`).

    ``finest_level`` is the last pyramid level refined (0 = full resolution); by default the
    finest with at most 8 megapixels (a prepared reference's own).

    A result is not ``ok`` when ECC fails to converge, its correlation on the finest level
    is below ``min_correlation``, or the warp is implausible for camera shake (shift above
    ``max_shift_frac`` of the width, rotation above ``max_rotation_deg``).
    """
    target = reference if isinstance(reference, Target) else prepare_target(reference, finest_level)
    if target.shape != shot.shape:
        raise AlignmentError(f"expected shots of equal size, got {target.shape} and {shot.shape}")
    if finest_level is not None and finest_level != target.finest_level:
        raise ValueError(f"expected finest_level {target.finest_level} (the prepared reference's), got {finest_level}")
    finest_level, levels = target.finest_level, target.finest_level + len(target.pyramid) - 1
    shots = _pyramid(shot, finest_level, levels - finest_level)
    warp = np.eye(3, dtype=np.float32) if motion is Motion.HOMOGRAPHY else np.eye(2, 3, dtype=np.float32)
    coarse_ref, coarse_shot = target.pyramid[-1][0], shots[-1][0]
    window = cv2.createHanningWindow(coarse_ref.shape[::-1], cv2.CV_32F)
    (dx, dy), _ = cv2.phaseCorrelate(coarse_ref.copy(), coarse_shot.copy(), window)    # it windows its inputs in place
    warp[0, 2], warp[1, 2] = dx, dy
    correlation = 0.0
    for level in range(levels, finest_level - 1, -1):
        (r, m), (s, n) = target.pyramid[level - finest_level], shots[level - finest_level]
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, *((300, 1e-8) if level == finest_level else (100, 1e-5)))
        if level < levels:
            warp = _scale_warp(warp, 2.0)
        try:
            correlation, warp = cv2.findTransformECCWithMask(r, s, m, n, warp, motion.cv_type, criteria, 3)
        except cv2.error as exc:
            return Alignment(_scale_warp(warp, 2.0**finest_level), 0.0, False, f"ECC did not converge at level {level}: {str(exc).splitlines()[-1]}")
    warp = _scale_warp(warp, 2.0**finest_level)
    width = target.shape[1]
    shift = float(np.hypot(warp[0, 2], warp[1, 2]))
    rotation = float(np.degrees(np.arctan2(warp[1, 0], warp[0, 0])))
    if correlation < min_correlation:
        return Alignment(warp, float(correlation), False, f"ECC correlation {correlation:.2f} below {min_correlation}")
    if shift > max_shift_frac * width or abs(rotation) > max_rotation_deg:
        return Alignment(warp, float(correlation), False, f"implausible warp: shift {shift:.1f} px, rotation {rotation:.2f} deg")
    return Alignment(warp, float(correlation), True)


def apply_warp(shot: np.ndarray, warp: np.ndarray) -> np.ndarray:
    """Resample ``shot`` onto the reference grid: out(x) = shot(W·x)."""
    h, w = shot.shape[:2]
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    if warp.shape[0] == 3:
        return cv2.warpPerspective(shot, warp, (w, h), flags=flags, borderMode=cv2.BORDER_REPLICATE)
    return cv2.warpAffine(shot, warp, (w, h), flags=flags, borderMode=cv2.BORDER_REPLICATE)
