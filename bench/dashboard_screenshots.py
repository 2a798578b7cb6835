"""Screenshots of the dashboard of a running `covslam serve`.

Run from the repository root, against a server that holds the map::

    python -m bench.dashboard_screenshots --url http://127.0.0.1:8000 --map ID \\
        --out bench/results/dashboard_NAME.png [--width 1280 --height 800] [--full-page]

Drives Debian's headless Chromium (``/usr/bin/chromium``, or ``--chromium``) through
Playwright; waits until the page shows the map's latest frame, then saves a PNG and
prints what the page's layers hold (their data attributes) as JSON.

The maps of docs/measurements.md ("Whole runs through the service"):
``bench.mrclam_http_all`` (MRCLAM-6, five robots, one map) and ``covslam simulate`` +
``covslam replay --url`` (a lifelong run);
``--width 390 --height 844 --full-page`` gives the phone-width pictures.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import httpx

from tests.e2e.chromium import CHROMIUM_ARGS


def screenshot(
    url: str,
    map_id: str,
    out: Path,
    *,
    width: int,
    height: int,
    full_page: bool,
    chromium: str,
    timeout_s: float = 120.0,
) -> dict[str, Any]:
    """Save the dashboard of `map_id` as a PNG; the layers' data attributes."""
    from playwright.sync_api import sync_playwright

    frames = httpx.get(f"{url}/v1/maps/{map_id}", timeout=60).json()["counts"]["frames"]
    errors: list[str] = []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": width, "height": height})
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(f"{url}/dashboard/?map={map_id}")
        page.wait_for_function(
            "n => document.getElementById('app').dataset.state === 'live' && "
            "Number(document.getElementById('app').dataset.frame) >= n",
            arg=frames,
            timeout=timeout_s * 1e3,
        )
        page.evaluate("window.covslamDashboard.draw()")
        page.wait_for_timeout(300)
        out.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(out), full_page=full_page)
        layers = page.evaluate(
            "() => Object.fromEntries([...document.querySelectorAll('[id]')]"
            ".filter(e => Object.keys(e.dataset).length).map(e => [e.id, {...e.dataset}]))"
        )
        browser.close()
    return {"map": map_id, "frames": frames, "png": str(out), "layers": layers, "errors": errors}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--url", required=True, help="the service, e.g. http://127.0.0.1:8000")
    ap.add_argument("--map", required=True, help="map id")
    ap.add_argument("--out", type=Path, required=True, help="PNG to write")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=800)
    ap.add_argument("--full-page", action="store_true", help="the whole page, not the viewport")
    ap.add_argument("--chromium", default="/usr/bin/chromium")
    args = ap.parse_args(argv)
    report = screenshot(
        args.url,
        args.map,
        args.out,
        width=args.width,
        height=args.height,
        full_page=args.full_page,
        chromium=args.chromium,
    )
    print(json.dumps(report, indent=1))
    return 1 if report["errors"] else 0


if __name__ == "__main__":
    sys.exit(main())
