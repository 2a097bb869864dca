"""The README's screenshot of `urd report --html` for the demo scene (docs/report/demo-report.png).

    python tools/report_screenshot.py [--out docs/report/demo-report.png] [--height 2600]

In a temporary folder: `urd demo` exactly as a new user runs it (its defaults: 1536×1024, seed 0;
it separates with the network), then `urd report --html`; the T̂ PSNR the demo printed must appear
on the page (the picture shows the demo's own numbers). Headless Chromium (selenium,
/usr/bin/chromium and /usr/bin/chromedriver) loads the report's index.html in a 1280 px wide
viewport (--height tall: the top of the page) and the screenshot is written as PNG (compression 9).
"""

import argparse
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from selenium import webdriver
from selenium.webdriver.chrome.service import Service

from toolargs import Formatter, positive

WIDTH = 1280


parser = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
parser.add_argument("--out", type=Path, default=Path("docs/report/demo-report.png"),
                    help="the PNG to write (replaced: the README's picture by default)")
parser.add_argument("--height", type=positive, default=2600, help="viewport height (px)")
parser.add_argument("--chromium", type=Path, default=Path("/usr/bin/chromium"), help="the Chromium binary")
parser.add_argument("--chromedriver", type=Path, default=Path("/usr/bin/chromedriver"), help="the chromedriver binary")
args = parser.parse_args()

for binary in (args.chromium, args.chromedriver):
    if not binary.is_file():
        sys.exit(f"{binary} not found: install chromium and chromedriver, or pass --chromium/--chromedriver")


def urd(*arguments: str) -> str:
    """Run the urd CLI of this interpreter and return what it printed; exit if it fails."""
    command = [sys.executable, "-m", "urd.cli", *arguments]
    done = subprocess.run(command, stdout=subprocess.PIPE, text=True)
    print(done.stdout, end="")
    if done.returncode != 0:
        sys.exit(f"failed: {' '.join(command)}")
    return done.stdout


def screenshot(page: Path) -> np.ndarray:
    """A WIDTH × --height screenshot of a page in headless Chromium, as a BGR image."""
    options = webdriver.ChromeOptions()
    options.binary_location = str(args.chromium)
    for flag in ("--headless=new", "--no-sandbox", "--hide-scrollbars", f"--window-size={WIDTH},{args.height}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(str(args.chromedriver)), options=options)
    try:
        driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride",
                               {"width": WIDTH, "height": args.height, "deviceScaleFactor": 1, "mobile": False})
        driver.get(page.as_uri())
        loaded = "return Array.from(document.images).every(image => image.complete && image.naturalWidth > 0)"
        deadline = time.monotonic() + 30
        while not driver.execute_script(loaded):          # lazy images load after the page: wait for them
            if time.monotonic() > deadline:
                sys.exit("the report's images did not load within 30 s")
            time.sleep(0.2)
        png = driver.get_screenshot_as_png()
    finally:
        driver.quit()
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)


with tempfile.TemporaryDirectory() as folder:
    dataset, report = Path(folder) / "demo", Path(folder) / "report"
    printed = urd("demo", str(dataset))
    urd("report", str(dataset), "--html", str(report))
    t_psnr = re.search(r"vs ground truth: T (\d+\.\d+) dB", printed)
    if t_psnr is None or f"{t_psnr.group(1)} dB" not in (report / "index.html").read_text(encoding="utf-8"):
        sys.exit("the report does not show the T̂ PSNR that urd demo printed")
    image = screenshot(report / "index.html")

if image.shape[:2] != (args.height, WIDTH):
    sys.exit(f"screenshot is {image.shape[1]}×{image.shape[0]} px, not {WIDTH}×{args.height}")
args.out.parent.mkdir(parents=True, exist_ok=True)
cv2.imwrite(str(args.out), image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
print(f"wrote {args.out.resolve()} ({WIDTH}×{args.height} px, {args.out.stat().st_size} bytes); "
      f"the demo printed T̂ {t_psnr.group(1)} dB and the page shows it")
