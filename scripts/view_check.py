"""`make view-check`: start `diffkin view`, open it in headless Chromium, save a screenshot, check it.

Starts ``diffkin view --robot panda`` (or the given robot / URDF options) on a free loopback port, opens the
page with Playwright driving a system Chromium (``/usr/bin/chromium``, WebGL through SwiftShader; no
``playwright install`` needed), waits for the scene to render, saves ``docs/img/viewer.png`` and checks that
the picture is not blank and that the robot's links (their orange) cover a reasonable part of the 3D view.

Usage::

    python scripts/view_check.py [--out docs/img/viewer.png] [--chromium /usr/bin/chromium] [-- VIEW ARGS]

Needs the ``viz`` extra and ``playwright`` (pip) and a Chromium (Debian: ``apt-get install chromium``).
Exit status 0 when the checks pass, 1 when they fail, 2 when something is missing.
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM_FLAGS = [
    "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
]
SEGMENT_RGB = (235, 120, 20)  # diffkin.viz draws the links in this orange


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_http(url: str, proc: subprocess.Popen, timeout: float) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise RuntimeError(f"`diffkin view` exited with status {proc.returncode}")
        try:
            with urllib.request.urlopen(url, timeout=2) as r:
                if r.status == 200:
                    return
        except OSError:
            time.sleep(0.3)
    raise RuntimeError(f"{url} did not answer within {timeout:.0f} s")


def analyse(png: Path) -> dict:
    """Pixel statistics of the screenshot: overall standard deviation and the share of link-orange pixels."""
    import numpy as np
    from PIL import Image

    img = np.asarray(Image.open(png).convert("RGB")).astype(np.float64)
    target = np.array(SEGMENT_RGB, dtype=np.float64)
    # lines are shaded/antialiased: orange-ish = red high, green in between, blue low
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    orange = (r > 150) & (g > 50) & (g < 190) & (b < 90) & (r - b > 110)
    near = np.linalg.norm(img - target, axis=-1) < 60
    return {"size": img.shape[1::-1], "std": float(img.std()), "orange_fraction": float(orange.mean()),
            "near_exact_fraction": float(near.mean())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "img" / "viewer.png"))
    ap.add_argument("--chromium", default=os.environ.get("CHROMIUM", shutil.which("chromium") or
                                                          "/usr/bin/chromium"))
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=800)
    ap.add_argument("--settle", type=float, default=4.0, help="seconds to let the scene render")
    ap.add_argument("--min-std", type=float, default=8.0, help="least pixel standard deviation (0-255)")
    ap.add_argument("--min-robot", type=float, default=0.002,
                    help="least fraction of the picture in the links' orange")
    ap.add_argument("view_args", nargs="*", help="arguments for `diffkin view` (default: --robot panda)")
    args = ap.parse_args(argv)

    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        print("error: view-check needs playwright: pip install playwright (no `playwright install`: "
              "it drives the system Chromium)", file=sys.stderr)
        return 2
    if not Path(args.chromium).is_file():
        print(f"error: no Chromium at {args.chromium} (Debian: apt-get install chromium; or --chromium PATH)",
              file=sys.stderr)
        return 2

    port = free_port()
    view_args = args.view_args or ["--robot", "panda"]
    cmd = [sys.executable, "-m", "diffkin.cli", "view", *view_args,
           "--host", "127.0.0.1", "--port", str(port)]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    print("$", " ".join(cmd[2:]), flush=True)
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        url = f"http://127.0.0.1:{port}"
        try:
            wait_http(url, proc, timeout=60)
        except RuntimeError as exc:
            proc.kill()
            print(proc.stdout.read() if proc.stdout else "", file=sys.stderr)
            print(f"error: {exc}", file=sys.stderr)
            return 1
        # playwright's launch() runs Chromium headless on a fresh temporary profile (its --user-data-dir)
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=args.chromium, headless=True, args=CHROMIUM_FLAGS)
            try:
                page = browser.new_page(viewport={"width": args.width, "height": args.height})
                logs: list[str] = []
                page.on("console", lambda m: logs.append(f"{m.type}: {m.text}"))
                page.goto(url, wait_until="load", timeout=60_000)
                page.wait_for_selector("canvas", timeout=60_000)
                # the scene arrives over the websocket after the page: poll until the links are drawn
                end = time.monotonic() + 60
                stats = None
                while time.monotonic() < end:
                    page.wait_for_timeout(1000)
                    page.screenshot(path=str(out))
                    stats = analyse(out)
                    if stats["orange_fraction"] >= args.min_robot:
                        break
                # viser's "Software WebGL rendering detected" notice (SwiftShader) would cover the view
                for button in page.locator(".mantine-Notification-root button").all():
                    try:
                        button.click(timeout=2000)
                    except Exception:  # gone already
                        pass
                page.wait_for_timeout(int(args.settle * 1000))  # let fonts, grid and GUI settle
                page.screenshot(path=str(out))
                stats = analyse(out)
                webgl = page.evaluate(
                    "() => { const c = document.createElement('canvas');"
                    " const g = c.getContext('webgl2') || c.getContext('webgl');"
                    " if (!g) return null; const d = g.getExtension('WEBGL_debug_renderer_info');"
                    " return d ? g.getParameter(d.UNMASKED_RENDERER_WEBGL) : g.getParameter(g.RENDERER); }")
            finally:
                browser.close()
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
    ok = stats["std"] >= args.min_std and stats["orange_fraction"] >= args.min_robot
    print(f"screenshot {out} {stats['size'][0]}x{stats['size'][1]}: pixel std {stats['std']:.1f} "
          f"(min {args.min_std}), robot (link orange) {100 * stats['orange_fraction']:.2f} % of the picture "
          f"(min {100 * args.min_robot:.2f} %); WebGL renderer: {webgl}")
    if not ok:
        print("error: the screenshot is blank or does not show the robot; browser console:", file=sys.stderr)
        print("\n".join(logs[-20:]), file=sys.stderr)
        return 1
    print("view-check: OK")
    return 0


if __name__ == "__main__":
    sys.exit(main())
