"""Line and grouped-bar plots drawn with OpenCV and written as PNG, atomically.

`plot_lines` draws series over categorical x (markers, optional error bars and zero line),
`plot_bars` grouped bars; both return the (H, W, 3) uint8 BGR image. Labels must be ASCII
(OpenCV's Hershey font).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from urd.core.files import atomic_path


#: Colours (BGR) of the series, matplotlib's "tab10".
PALETTE = ((180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148), (75, 86, 140),
           (194, 119, 227), (127, 127, 127), (34, 189, 188), (207, 190, 23))
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def nice_ticks(lo: float, hi: float, count: int = 6) -> list[float]:
    """Round tick values (steps 1, 2, 2.5 or 5 × 10^k) from at or below ``lo`` to at or above
    ``hi``, about ``count`` of them."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"expected finite limits, got {lo}, {hi}")
    if hi <= lo:
        lo, hi = lo - 0.5, hi + 0.5
    raw = (hi - lo) / max(count - 1, 1)
    magnitude = 10 ** math.floor(math.log10(raw))
    step = next(m * magnitude for m in (1, 2, 2.5, 5, 10) if m * magnitude >= raw * (1 - 1e-9))
    start, stop = math.floor(lo / step + 1e-9), math.ceil(hi / step - 1e-9)
    return [round(k * step, 10) for k in range(start, stop + 1)]


def _text(canvas: np.ndarray, text: str, x: int, y: int, scale: float = 0.45, align: str = "left",
          colour: tuple[int, int, int] = (0, 0, 0)) -> None:
    """Draw ``text`` on ``canvas`` vertically centred on row ``y``, aligned at column ``x`` (left, center, right)."""
    (w, h), _ = cv2.getTextSize(text, _FONT, scale, 1)
    x = x - w // 2 if align == "center" else x - w if align == "right" else x
    cv2.putText(canvas, text, (int(x), int(y + h // 2)), _FONT, scale, colour, 1, cv2.LINE_AA)


def _tick_label(value: float, step: float) -> str:
    """A tick value with as many decimals as the tick step needs."""
    decimals = max(0, -math.floor(math.log10(step) + 1e-9)) if step < 1 else 0
    decimals += 1 if step * 10 ** decimals % 1 else 0
    return f"{value:.{decimals}f}"


def _frame(size: tuple[int, int], title: str, x_labels: Sequence[str], x_title: str, y_title: str,
           ticks: list[float], series: Sequence[str]) -> tuple[np.ndarray, Callable[[float], int], Callable[[float], float], tuple]:
    """A white canvas with title, grid, axes, categorical x labels, y ticks and a legend; returns
    (canvas, y → row, slot index → column centre, plot box (x0, y0, x1, y1))."""
    width, height = size
    canvas = np.full((height, width, 3), 255, np.uint8)
    legend_w = 20 + max([cv2.getTextSize(s, _FONT, 0.45, 1)[0][0] for s in series] + [0]) + 30 if series else 0
    x0, y0, x1, y1 = 78, 46, width - 16 - legend_w, height - 62
    if x1 - x0 < 100 or y1 - y0 < 100:
        raise ValueError(f"expected a plot of at least {x0 + 116 + legend_w} × {y0 + 162} px, got {width} × {height}")
    lo, hi = ticks[0], ticks[-1]

    def row(y: float) -> int:
        return int(round(y1 - (y - lo) / (hi - lo) * (y1 - y0)))

    slot = (x1 - x0) / max(len(x_labels), 1)

    def column(i: float) -> float:
        return x0 + (i + 0.5) * slot

    step = ticks[1] - ticks[0] if len(ticks) > 1 else 1.0
    for value in ticks:
        cv2.line(canvas, (x0, row(value)), (x1, row(value)), (225, 225, 225), 1)
        cv2.line(canvas, (x0 - 5, row(value)), (x0, row(value)), (0, 0, 0), 1)
        _text(canvas, _tick_label(value, step), x0 - 8, row(value), align="right")
    for i, label in enumerate(x_labels):
        cx = int(round(column(i)))
        cv2.line(canvas, (cx, y1), (cx, y1 + 5), (0, 0, 0), 1)
        _text(canvas, label, cx, y1 + 16, scale=0.42 if len(x_labels) < 10 else 0.36, align="center")
    cv2.rectangle(canvas, (x0, y0), (x1, y1), (0, 0, 0), 1)
    _text(canvas, title, (x0 + x1) // 2, 22, scale=0.55, align="center")
    _text(canvas, x_title, (x0 + x1) // 2, height - 18, align="center")
    (tw, th), _ = cv2.getTextSize(y_title, _FONT, 0.45, 1)
    label = np.full((th + 10, tw + 4, 3), 255, np.uint8)
    _text(label, y_title, 2, (th + 10) // 2)
    label = cv2.rotate(label, cv2.ROTATE_90_COUNTERCLOCKWISE)
    top = max(0, (y0 + y1) // 2 - label.shape[0] // 2)
    label = label[: height - top]
    canvas[top : top + label.shape[0], 8 : 8 + label.shape[1]] = np.minimum(canvas[top : top + label.shape[0], 8 : 8 + label.shape[1]], label)
    lx = x1 + 16
    for i, name in enumerate(series):
        ly = y0 + 10 + 20 * i
        cv2.line(canvas, (lx, ly), (lx + 22, ly), PALETTE[i % len(PALETTE)], 3, cv2.LINE_AA)
        _text(canvas, name, lx + 30, ly)
    return canvas, row, column, (x0, y0, x1, y1)


def _limits(values: list[float], floor: float | None = None) -> list[float]:
    """Ticks covering the finite values with 5% margin (and ``floor`` when given); [0, 1] without any."""
    finite = [v for v in values if math.isfinite(v)] or [0.0, 1.0]
    lo, hi = min(finite), max(finite)
    pad = 0.05 * (hi - lo) if hi > lo else 0.5
    return nice_ticks(lo - pad if floor is None else min(floor, lo - pad), hi + pad)


def write_png(path: Path, image: np.ndarray) -> None:
    """Write an 8-bit BGR image as PNG, atomically."""
    path = Path(path)
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise ValueError(f"cannot encode a PNG of shape {image.shape} for {path}")
    with atomic_path(path, overwrite=True) as tmp:
        tmp.write_bytes(data.tobytes())


def plot_lines(path: Path | None, x_labels: Sequence[str], series: dict[str, Sequence[float]], title: str, x_title: str,
               y_title: str, intervals: dict[str, Sequence[tuple[float, float]]] | None = None,
               size: tuple[int, int] = (900, 540), zero_line: bool = False, connect: bool = True) -> np.ndarray:
    """A line plot over categorical x (one marker per level, NaN leaves a gap; ``connect``
    False: markers only), with optional error bars (``intervals``: name → (lo, hi) per level)
    and a line at 0 (``zero_line``), written as PNG to ``path`` unless None.

    Returns the (size[1], size[0], 3) uint8 BGR image. Labels must be ASCII (OpenCV's font).
    """
    for name, values in series.items():
        if len(values) != len(x_labels):
            raise ValueError(f"expected {len(x_labels)} values for series {name!r}, got {len(values)}")
    values = [v for vs in series.values() for v in vs] + [v for iv in (intervals or {}).values() for pair in iv for v in pair]
    ticks = _limits(values + ([0.0] if zero_line else []))
    canvas, row, column, (x0, _, x1, _) = _frame(size, title, x_labels, x_title, y_title, ticks, list(series))
    if zero_line:
        cv2.line(canvas, (x0, row(0.0)), (x1, row(0.0)), (90, 90, 90), 1, cv2.LINE_AA)
    count = max(len(series), 1)
    for k, (name, ys) in enumerate(series.items()):
        colour = PALETTE[k % len(PALETTE)]
        nudge = (k - (count - 1) / 2) * 3 if intervals else 0
        points = [(int(round(column(i) + nudge)), row(y)) if math.isfinite(y) else None for i, y in enumerate(ys)]
        for a, b in zip(points, points[1:]):
            if connect and a and b:
                cv2.line(canvas, a, b, colour, 2, cv2.LINE_AA)
        for i, p in enumerate(points):
            if p is None:
                continue
            if intervals and name in intervals:
                lo, hi = intervals[name][i]
                if math.isfinite(lo) and math.isfinite(hi):
                    cv2.line(canvas, (p[0], row(lo)), (p[0], row(hi)), colour, 1, cv2.LINE_AA)
                    for v in (lo, hi):
                        cv2.line(canvas, (p[0] - 4, row(v)), (p[0] + 4, row(v)), colour, 1, cv2.LINE_AA)
            cv2.circle(canvas, p, 4, colour, -1, cv2.LINE_AA)
    if path is not None:
        write_png(path, canvas)
    return canvas


def plot_bars(path: Path | None, groups: Sequence[str], series: dict[str, Sequence[float]], title: str, y_title: str,
              x_title: str = "", size: tuple[int, int] = (900, 540)) -> np.ndarray:
    """Grouped bars (a group per x label, a bar per series; NaN: no bar) from the lowest tick
    up, written as PNG to ``path`` unless None; returns the image as `plot_lines` does."""
    for name, values in series.items():
        if len(values) != len(groups):
            raise ValueError(f"expected {len(groups)} values for series {name!r}, got {len(values)}")
    values = [v for vs in series.values() for v in vs]
    ticks = _limits(values)
    canvas, row, column, (x0, _, x1, _) = _frame(size, title, groups, x_title, y_title, ticks, list(series))
    slot = (x1 - x0) / max(len(groups), 1)
    bar = 0.8 * slot / max(len(series), 1)
    for k, (_, ys) in enumerate(series.items()):
        for i, y in enumerate(ys):
            if not math.isfinite(y):
                continue
            left = column(i) - 0.4 * slot + k * bar
            cv2.rectangle(canvas, (int(round(left)), row(y)), (int(round(left + bar)) - 1, row(ticks[0]) - 1),
                          PALETTE[k % len(PALETTE)], -1)
    if path is not None:
        write_png(path, canvas)
    return canvas
