"""The HTML report's drawings, style sheet and script (`urd.report_html`): the AoLP colour wheel,
the calibration plot and the comparison slider as SVG/HTML, and the page's layout and viewer,
inlined so that the report opens from disk."""

from __future__ import annotations

import html
import math
from typing import TYPE_CHECKING
from urllib.parse import quote

import numpy as np

if TYPE_CHECKING:
    from urd.report_html import CalibrationView

_e = html.escape


def wheel_svg(uid: str, reference_deg: float | None, radius: int = 46) -> str:
    """AoLP legend: a disc whose direction a (image-plane convention, counter-clockwise from +x)
    has the hue of AoLP = a mod 180°, fading to white (unpolarized) at the centre; the
    reference angle is drawn as a dashed diameter."""
    c = radius + 22
    parts = [f'<svg class="wheel" width="{2 * c}" height="{2 * c}" viewBox="0 0 {2 * c} {2 * c}" role="img" '
             f'aria-label="AoLP colour wheel"><defs><radialGradient id="{uid}">'
             '<stop offset="0" stop-color="#fff" stop-opacity="1"/><stop offset="1" stop-color="#fff" stop-opacity="0"/>'
             "</radialGradient></defs>"]
    step = 5
    for a in range(0, 360, step):
        hue = (2 * (a % 180)) % 360
        a0, a1 = math.radians(a - step / 2 - 0.4), math.radians(a + step / 2 + 0.4)
        x0, y0 = c + radius * math.cos(a0), c - radius * math.sin(a0)
        x1, y1 = c + radius * math.cos(a1), c - radius * math.sin(a1)
        parts.append(f'<path d="M{c},{c} L{x0:.2f},{y0:.2f} A{radius},{radius} 0 0 0 {x1:.2f},{y1:.2f} Z" '
                     f'fill="hsl({hue},100%,50%)"/>')
    parts.append(f'<circle cx="{c}" cy="{c}" r="{radius}" fill="url(#{uid})" stroke="#9aa3b2" stroke-width="0.8"/>')
    for a in (0, 45, 90, 135):
        x, y = c + (radius + 12) * math.cos(math.radians(a)), c - (radius + 12) * math.sin(math.radians(a))
        parts.append(f'<text x="{x:.1f}" y="{y + 4:.1f}" text-anchor="middle">{a}°</text>')
    if reference_deg is not None and math.isfinite(reference_deg):
        r = math.radians(reference_deg)
        dx, dy = (radius + 4) * math.cos(r), -(radius + 4) * math.sin(r)
        parts.append(f'<line x1="{c - dx:.2f}" y1="{c - dy:.2f}" x2="{c + dx:.2f}" y2="{c + dy:.2f}" '
                     'stroke="#111" stroke-width="1.6" stroke-dasharray="4 3"/>')
    parts.append("</svg>")
    return "".join(parts)


def nice_ticks(lo: float, hi: float, count: int = 5) -> list[float]:
    span = hi - lo if hi > lo else 1.0
    raw = span / count
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
    first = math.ceil(lo / step) * step
    return [first + i * step for i in range(int((hi - first) / step + 1e-9) + 1)]


def calibration_svg(cal: CalibrationView) -> str:
    """The sweep (points), the Malus-law fit (curve) and the fitted maximum ± uncertainty."""
    width, height, left, right, top, bottom = 640, 280, 58, 16, 14, 40
    xs = [float(a) for a in [*cal.angles_deg, *cal.fit_angles_deg]]
    ys = [float(v) for v in [*cal.intensities, *cal.fit_intensities]]
    x_lo, x_hi = (0.0, 180.0) if min(xs) >= 0 and max(xs) <= 180 else (min(xs), max(xs))
    y_lo, y_hi = 0.0, max(max(ys) * 1.08, 1e-12)
    if min(ys) < 0:
        y_lo = min(ys) * 1.08

    def px(x: float) -> float:
        return left + (x - x_lo) / (x_hi - x_lo) * (width - left - right)

    def py(y: float) -> float:
        return height - bottom - (y - y_lo) / (y_hi - y_lo) * (height - top - bottom)

    parts = [f'<svg class="plot" width="{width}" height="{height}" viewBox="0 0 {width} {height}" role="img" '
             'aria-label="Malus-law sweep and fit">']
    for y in nice_ticks(y_lo, y_hi, 4):
        parts.append(f'<line class="grid" x1="{left}" x2="{width - right}" y1="{py(y):.1f}" y2="{py(y):.1f}"/>'
                     f'<text x="{left - 6}" y="{py(y) + 4:.1f}" text-anchor="end">{y:.3g}</text>')
    x_ticks = np.arange(math.ceil(x_lo / 30) * 30, x_hi + 1e-9, 30.0).tolist() if x_hi - x_lo >= 90 else nice_ticks(x_lo, x_hi, 6)
    for x in x_ticks:
        parts.append(f'<line class="grid" y1="{top}" y2="{height - bottom}" x1="{px(x):.1f}" x2="{px(x):.1f}"/>'
                     f'<text x="{px(x):.1f}" y="{height - bottom + 16}" text-anchor="middle">{x:g}°</text>')
    parts.append(f'<text x="{(left + width - right) / 2}" y="{height - 6}" text-anchor="middle">stage angle</text>'
                 f'<text transform="translate(14,{(top + height - bottom) / 2}) rotate(-90)" text-anchor="middle">'
                 "mean intensity</text>")
    if cal.fit_intensities:
        peak = float(cal.fit_angles_deg[int(np.argmax(cal.fit_intensities))])
        u = abs(float(cal.uncertainty_deg))
        band_lo, band_hi = max(x_lo, peak - u), min(x_hi, peak + u)
        parts.append(f'<rect class="band" x="{px(band_lo):.1f}" y="{top}" width="{max(px(band_hi) - px(band_lo), 1):.1f}" '
                     f'height="{height - top - bottom}"/>'
                     f'<line class="peak" x1="{px(peak):.1f}" x2="{px(peak):.1f}" y1="{top}" y2="{height - bottom}"/>')
        points = " ".join(f"{px(float(x)):.1f},{py(float(y)):.1f}" for x, y in zip(cal.fit_angles_deg, cal.fit_intensities))
        parts.append(f'<polyline class="fit" points="{points}"/>')
    for x, y in zip(cal.angles_deg, cal.intensities):
        parts.append(f'<circle class="pt" cx="{px(float(x)):.1f}" cy="{py(float(y)):.1f}" r="3.5"/>')
    parts.append(f'<rect class="frame" x="{left}" y="{top}" width="{width - left - right}" height="{height - top - bottom}"/>'
                 "</svg>")
    return "".join(parts)


def compare_html(options: list[tuple[str, str]], left: int, right: int, size: tuple[int, int], anchor: str,
                  thumb_px: int) -> str:
    """Two selects of (relative path, label) ``options`` showing ``left`` and ``right`` first, a stage
    with the right image under the left one clipped at the divider, and a range input; ``size``
    (H, W) is that of every view of the scene (checked on entry). Paths are percent-encoded."""
    values, labels = [quote(v) for v, _ in options], [label for _, label in options]
    h, w = size
    mid_w = max(round(w * min(1.0, 2 * thumb_px / max(h, w))), 360)

    def select(cls: str, chosen: int, side: str) -> str:
        opts = "".join(f'<option value="{_e(v)}"{" selected" if i == chosen else ""}>{_e(label)}</option>'
                       for i, (v, label) in enumerate(zip(values, labels)))
        return f'<label>{side} <select class="cmp-select {cls}" aria-label="{side} image">{opts}</select></label>'

    return (f'<div class="compare" data-scene="{anchor}"><h3>Compare</h3><div class="cmp-controls">'
            f'{select("cmp-left", left, "left")}{select("cmp-right", right, "right")}'
            '<span class="muted small">drag on the image or use the slider</span></div>'
            f'<div class="cmp-stage" style="aspect-ratio: {w} / {h}; max-width: {mid_w}px">'
            f'<img class="cmp-b" src="{_e(values[right])}" loading="lazy" alt="right image">'
            f'<img class="cmp-a" src="{_e(values[left])}" loading="lazy" alt="left image">'
            '<div class="cmp-divider"></div><span class="cmp-tag left"></span><span class="cmp-tag right"></span></div>'
            f'<input class="cmp-range" type="range" min="0" max="100" step="0.5" value="50" aria-label="divider position" '
            f'style="max-width: {mid_w}px">'
            "</div>")


#: The page's style sheet.
CSS = """
:root { --fg:#1c2330; --muted:#5d6879; --line:#dfe3ea; --bg:#f4f5f8; --card:#fff; --accent:#2563eb; }
* { box-sizing: border-box; }
body { margin: 0; background: var(--bg); color: var(--fg);
  font: 14px/1.5 system-ui, -apple-system, "Segoe UI", Roboto, "Helvetica Neue", Arial, sans-serif; }
main { max-width: 1320px; margin: 0 auto; padding: 28px 24px 60px; }
header h1 { font-size: 26px; margin: 0 0 2px; letter-spacing: -0.01em; }
h2 { font-size: 19px; margin: 0; word-break: break-word; }
h3 { font-size: 12px; font-weight: 600; text-transform: uppercase; letter-spacing: .07em; color: var(--muted);
  margin: 22px 0 10px; }
a { color: var(--accent); }
.best { margin: 4px 0 10px; }
.muted { color: var(--muted); } .small { font-size: 12px; }
.card { background: var(--card); border: 1px solid var(--line); border-radius: 10px; padding: 20px 22px; margin: 18px 0;
  box-shadow: 0 1px 2px rgba(20,30,50,.04); }
.row { display: flex; flex-wrap: wrap; gap: 14px; align-items: flex-start; }
.row.strip { flex-wrap: nowrap; overflow-x: auto; padding-bottom: 2px; }
figure { margin: 0; max-width: 100%; }
figure img { display: block; max-width: 100%; height: auto; border-radius: 4px; background: #e8ebf0; }
figure a.zoom { display: block; cursor: zoom-in; }
figcaption { font-size: 12px; color: var(--muted); margin-top: 5px; }
.err { display: inline-block; margin-left: 6px; color: #8a5a00; }
.scene-head { display: flex; flex-wrap: wrap; align-items: baseline; gap: 10px 16px; }
.meta { display: flex; flex-wrap: wrap; gap: 8px 14px; align-items: baseline; }
.fact { color: var(--muted); } .fact b { color: var(--fg); }
.badge { display: inline-block; padding: 1px 9px; border-radius: 999px; font-size: 12px; font-weight: 600;
  background: #eef0f4; color: #404a5a; border: 1px solid #dde1e8; }
.badge.separated { background: #e7f6ec; color: #17663a; border-color: #c3e8cf; }
.badge.ingested { background: #e8f0fe; color: #1f4fb3; border-color: #c8d8fb; }
.badge.incomplete, .badge.captured { background: #fff5e0; color: #8a5a00; border-color: #f3dfb0; }
.badge.broken { background: #fde8e8; color: #a12020; border-color: #f5c6c6; }
ul.notes { margin: 12px 0 0; padding: 8px 12px 8px 30px; background: #fff8e6; border: 1px solid #f3e1b5;
  border-radius: 6px; color: #6b4a00; }
.colorbar { width: 100%; margin-top: 6px; }
.colorbar .ramp { height: 10px; border-radius: 3px; border: 1px solid #cfd5de; }
.colorbar .ticks { display: flex; justify-content: space-between; font-size: 11px; color: var(--muted); }
figure.legend { text-align: center; margin-left: 8px; }
figure.legend figcaption { margin: 0 auto; max-width: 170px; }
svg text { font: 11px system-ui, sans-serif; fill: #4a5566; }
.method { border-top: 1px solid var(--line); padding: 12px 0 4px; }
.method:first-of-type { border-top: 0; }
.method-name { font-weight: 600; margin-bottom: 8px; word-break: break-word; }
details.prov { margin-top: 8px; }
details.prov summary { cursor: pointer; color: var(--accent); font-size: 13px; }
table.kv { border-collapse: collapse; margin-top: 6px; font-size: 12px; }
table.kv th, table.kv td { text-align: left; vertical-align: top; padding: 3px 12px 3px 0; border-bottom: 1px solid #eef0f3; }
table.kv th { color: var(--muted); font-weight: 500; white-space: nowrap; }
table.kv pre { margin: 0; font-size: 11px; white-space: pre-wrap; word-break: break-word; }
.compare { margin-top: 6px; }
.cmp-controls { display: flex; flex-wrap: wrap; gap: 10px 18px; align-items: center; margin-bottom: 8px; }
.cmp-controls select { font: inherit; padding: 3px 6px; border-radius: 5px; border: 1px solid #c9cfd9; background: #fff; }
.cmp-stage { position: relative; width: 100%; overflow: hidden; border-radius: 6px; background: #e8ebf0;
  cursor: ew-resize; touch-action: none; user-select: none; }
.cmp-stage img { position: absolute; inset: 0; width: 100%; height: 100%; display: block; pointer-events: none; }
.cmp-divider { position: absolute; top: 0; bottom: 0; left: 50%; width: 2px; margin-left: -1px; background: #fff;
  box-shadow: 0 0 0 1px rgba(0,0,0,.35); pointer-events: none; }
.cmp-divider::after { content: "\\2194"; position: absolute; top: 50%; left: 50%; transform: translate(-50%, -50%);
  width: 26px; height: 26px; border-radius: 50%; background: #fff; color: #333; font-size: 15px; line-height: 26px;
  text-align: center; box-shadow: 0 1px 4px rgba(0,0,0,.4); }
.cmp-range { width: 100%; display: block; margin-top: 8px; }
.cmp-tag { position: absolute; top: 8px; padding: 1px 8px; border-radius: 4px; font-size: 12px; color: #fff;
  background: rgba(12,16,24,.62); pointer-events: none; max-width: 45%; overflow: hidden; text-overflow: ellipsis;
  white-space: nowrap; }
.cmp-tag.left { left: 8px; } .cmp-tag.right { right: 8px; }
nav.toc .scroll { overflow-x: auto; }
nav.toc table { border-collapse: collapse; width: 100%; font-size: 13px; }
nav.toc th, nav.toc td { text-align: left; padding: 6px 10px 6px 0; border-bottom: 1px solid #eef0f3; }
nav.toc th { color: var(--muted); font-weight: 500; }
dl.facts { display: grid; grid-template-columns: auto 1fr; gap: 6px 14px; margin: 6px 0; align-content: start; }
dl.facts dt { color: var(--muted); } dl.facts dd { margin: 0; }
.plotbox { max-width: 100%; overflow-x: auto; }
svg.plot .grid { stroke: #e6e9ef; } svg.plot .frame { fill: none; stroke: #b8c0cc; }
svg.plot .fit { fill: none; stroke: var(--accent); stroke-width: 2; }
svg.plot .pt { fill: #fff; stroke: #1c2330; stroke-width: 1.5; }
svg.plot .band { fill: rgba(234,88,12,.14); } svg.plot .peak { stroke: #ea580c; stroke-dasharray: 5 4; }
.howto ul { margin: 6px 0 0; padding-left: 20px; }
#viewer { position: fixed; inset: 0; background: rgba(12,16,24,.92); z-index: 10; overflow: auto; display: flex;
  flex-direction: column; align-items: flex-start; justify-content: flex-start; padding: 44px 16px 16px; }
#viewer .holder { margin: 0 auto; }
#viewer[hidden] { display: none; }
#viewer img { max-width: 96vw; max-height: calc(100vh - 90px); cursor: zoom-in; box-shadow: 0 4px 30px rgba(0,0,0,.5); }
#viewer img.actual { max-width: none; max-height: none; cursor: zoom-out; }
#viewer .bar { position: fixed; top: 0; left: 0; right: 0; display: flex; justify-content: space-between; align-items: center;
  padding: 8px 14px; color: #e7ebf2; font-size: 13px; background: #0c1018; z-index: 1; }
#viewer button { font: inherit; color: #fff; background: #2b3341; border: 1px solid #4a5466; border-radius: 5px;
  padding: 2px 10px; cursor: pointer; }
"""

#: The viewer and comparison slider.
JS = """
(function () {
  'use strict';
  var viewer = document.getElementById('viewer');
  var caption = viewer.querySelector('.caption');
  var holder = viewer.querySelector('.holder');
  function closeViewer() { viewer.hidden = true; holder.textContent = ''; }
  function openViewer(href, text) {
    holder.textContent = '';
    var img = document.createElement('img');
    img.alt = text; img.src = href;
    img.addEventListener('click', function (e) { e.stopPropagation(); img.classList.toggle('actual'); });
    holder.appendChild(img);
    caption.textContent = text + ' (full resolution; click the image for 1:1, Esc to close)';
    viewer.hidden = false;
  }
  document.addEventListener('click', function (e) {
    var a = e.target.closest && e.target.closest('a.zoom');
    if (!a || e.button !== 0 || e.ctrlKey || e.metaKey || e.shiftKey) return;
    e.preventDefault();
    openViewer(a.getAttribute('href'), a.dataset.caption || '');
  });
  viewer.addEventListener('click', function (e) { if (e.target === viewer || e.target === holder || e.target.closest('button')) closeViewer(); });
  document.addEventListener('keydown', function (e) { if (e.key === 'Escape' && !viewer.hidden) closeViewer(); });

  Array.prototype.forEach.call(document.querySelectorAll('.compare'), function (box) {
    var left = box.querySelector('.cmp-left'), right = box.querySelector('.cmp-right');
    var imgA = box.querySelector('.cmp-a'), imgB = box.querySelector('.cmp-b');
    var stage = box.querySelector('.cmp-stage'), divider = box.querySelector('.cmp-divider');
    var range = box.querySelector('.cmp-range');
    var tagA = box.querySelector('.cmp-tag.left'), tagB = box.querySelector('.cmp-tag.right');
    function labels() {
      tagA.textContent = left.options[left.selectedIndex].text;
      tagB.textContent = right.options[right.selectedIndex].text;
    }
    function update() {
      var v = Number(range.value);
      imgA.style.clipPath = 'inset(0 ' + (100 - v) + '% 0 0)';
      divider.style.left = v + '%';
    }
    function fromPointer(e) {
      var r = stage.getBoundingClientRect();
      range.value = String(Math.max(0, Math.min(100, 100 * (e.clientX - r.left) / r.width)));
      update();
    }
    range.addEventListener('input', update);
    left.addEventListener('change', function () { imgA.src = left.value; labels(); });
    right.addEventListener('change', function () { imgB.src = right.value; labels(); });
    stage.addEventListener('pointerdown', function (e) {
      stage.setPointerCapture(e.pointerId); fromPointer(e);
      function move(ev) { fromPointer(ev); }
      function up() { stage.removeEventListener('pointermove', move); stage.removeEventListener('pointerup', up); }
      stage.addEventListener('pointermove', move); stage.addEventListener('pointerup', up);
    });
    labels(); update();
  });
})();
"""
