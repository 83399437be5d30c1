"""The screenshot of ``kpcn view`` under reports/: the page served for a frame and a run, driven in
headless Chromium (:mod:`kpcn_keras.studies.browser`: Debian's chromium and chromium-driver, Selenium)
as a user drives it: one brush stroke at the top of the λ range across the middle of the frame (λ at the low
end elsewhere), then kpcn left of the swipe and the λ map right of it, the swipe at the frame's middle; the
page's own status line says what the stroke cost.

  .venv/bin/python -m kpcn_keras.studies.view_screenshot --run runs/lambda-mixture --frame F.exr --reference R.exr
                                              [--out reports/view.png]
"""

from __future__ import annotations

import argparse
import tempfile
import threading
from pathlib import Path

from kpcn_keras.studies.browser import browser_missing, headless_chromium, page_input, page_stroke, page_wait
from kpcn_keras.viewer import ViewSession, listen


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True)
    parser.add_argument("--frame", required=True)
    parser.add_argument("--reference")
    parser.add_argument("--slope", type=float, help="λ everywhere before the stroke (default: the range's low end)")
    parser.add_argument("--out", default="reports/view.png")
    args = parser.parse_args()
    if browser_missing():
        raise SystemExit(f"error: {browser_missing()}")

    from kpcn_keras.run import Run
    from prep.processes import keep_freed_memory

    keep_freed_memory()  # as kpcn view does (kpcn_keras.cli.main)
    run = Run(args.run)
    low = run.record().train.slope_range[0]
    session = ViewSession.open(args.frame, run, args.reference, slope=args.slope or low)
    httpd = listen(0)
    httpd.session = session
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    try:
        with tempfile.TemporaryDirectory() as profile, headless_chromium(Path(profile)) as driver:
            driver.get(f"http://127.0.0.1:{httpd.server_address[1]}/")
            page_wait(driver, "window.kpcn && kpcn.ready", 120)
            driver.find_element("css selector", "input[name=mode][value=paint]").click()
            page_input(driver, "brush-radius", 30)
            page_input(driver, "brush-slope", 1)
            h, w = session.shape
            page_stroke(driver, [((0.2 + 0.6 * t / 8) * w, (0.5 - 0.15 * (t % 2)) * h) for t in range(9)])
            page_wait(driver, "kpcn.state.strokes === 1 && !kpcn.busy()", 120)
            # kpcn left of the swipe, the λ map right of it, the swipe at the frame's middle; no brush circle
            page_input(driver, "left", "denoised")
            page_input(driver, "right", "lambda")
            page_input(driver, "split", driver.execute_script(
                "const s = kpcn.state; return (s.ox + 0.5 * s.info.width * s.zoom) / "
                "document.getElementById('canvas').width;"))
            driver.execute_script("kpcn.state.mouse = null; draw();")
            Path(args.out).parent.mkdir(parents=True, exist_ok=True)
            driver.save_screenshot(args.out)
            print(driver.find_element("id", "status").text)
            print(f"wrote {args.out}")
    finally:
        httpd.shutdown()
        httpd.server_close()


if __name__ == "__main__":
    main()
