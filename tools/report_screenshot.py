"""The README's screenshot of `urd report --html` for the demo scene (docs/report/demo-report.png).

    python tools/report_screenshot.py [--out docs/report/demo-report.png] [--height 3200]

In a temporary folder: `urd demo` at 512×384 (seed 0; it separates with the network), `urd separate`
with Schechner's method, `urd report --html`; then headless Chromium (selenium, /usr/bin/chromium and
/usr/bin/chromedriver) loads the report's index.html in a 1280 px wide viewport (--height tall: the top
of the page) and the screenshot is written as PNG (compression 9).
"""

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
from selenium import webdriver
from selenium.webdriver.chrome.service import Service

WIDTH = 1280

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--out", type=Path, default=Path("docs/report/demo-report.png"))
parser.add_argument("--height", type=int, default=3200, help="viewport height (px)")
parser.add_argument("--chromium", type=Path, default=Path("/usr/bin/chromium"))
parser.add_argument("--chromedriver", type=Path, default=Path("/usr/bin/chromedriver"))
args = parser.parse_args()

for binary in (args.chromium, args.chromedriver):
    if not binary.is_file():
        sys.exit(f"{binary} not found: install chromium and chromedriver, or pass --chromium/--chromedriver")


def urd(*arguments: str) -> None:
    """Run the urd CLI of this interpreter; exit if it fails."""
    command = [sys.executable, "-m", "urd.cli", *arguments]
    if subprocess.run(command).returncode != 0:
        sys.exit(f"failed: {' '.join(command)}")


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
        png = driver.get_screenshot_as_png()
    finally:
        driver.quit()
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)


with tempfile.TemporaryDirectory() as folder:
    dataset, report = Path(folder) / "demo", Path(folder) / "report"
    urd("demo", str(dataset), "--size", "512x384", "--seed", "0")
    urd("separate", "scene_01", "--dataset", str(dataset), "--method", "schechner")
    urd("report", str(dataset), "--html", str(report))
    image = screenshot(report / "index.html")

if image.shape[:2] != (args.height, WIDTH):
    sys.exit(f"screenshot is {image.shape[1]}×{image.shape[0]} px, not {WIDTH}×{args.height}")
args.out.parent.mkdir(parents=True, exist_ok=True)
cv2.imwrite(str(args.out), image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
print(f"wrote {args.out.resolve()} ({WIDTH}×{args.height} px, {args.out.stat().st_size} bytes)")
