"""Check the built site in a headless browser: the mathematics renders and the images load.

    python docs/browser_check.py [SITE_DIR]      # after `mkdocs build`; SITE_DIR defaults to site/

Serves SITE_DIR on a local port and opens three pages in headless Chromium (the `chromium` and
`chromium-driver` packages of Debian; nothing is downloaded at run time): the home page, the
rigid-body tutorial (a notebook rendered with its plots) and an API page (docstrings with
maths). On each it waits for MathJax to finish and asserts that

- every formula was typeset (no math left as TeX source, no MathJax error),
- every image loaded (its natural width is positive),
- every resource the page asked for came from the site itself (nothing from a CDN) and was there,

and saves a screenshot of the page under docs/screenshots/ (CI keeps them as artifacts). Exits 1
with the failures listed, 0 when every page passes.
"""

from __future__ import annotations

import functools
import http.server
import pathlib
import shutil
import sys
import threading

from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.support.ui import WebDriverWait

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCREENSHOTS = ROOT / "docs" / "screenshots"

PAGES = {
    "home": "index.html",
    "tutorial": "notebooks/02_rigid_body/index.html",
    "api": "api/systems/index.html",
}
"""Screenshot name → page, relative to the site directory."""

MIN_FORMULAS = {"home": 5, "tutorial": 5, "api": 5}
MIN_IMAGES = {"home": 1, "tutorial": 2, "api": 0}

# Runs in the page once MathJax has finished: what was typeset, what was not, what loaded.
# Maths left untypeset shows as its TeX delimiters in the page's text (code blocks excepted).
_INSPECT = r"""
const rendered = document.querySelectorAll('mjx-container').length;
const pending = [...document.querySelectorAll('.arithmatex')].filter(
    el => !el.querySelector('mjx-container')).map(el => el.textContent.slice(0, 60));
const walker = document.createTreeWalker(document.querySelector('article') || document.body, NodeFilter.SHOW_TEXT);
for (let node; (node = walker.nextNode());) {
    if (node.parentElement.closest('pre, code, script, style, mjx-container')) continue;
    const tex = node.textContent.match(/\\\(|\\\[|\$\$|\$[^$\s][^$]*\$/);
    if (tex) pending.push(node.textContent.slice(Math.max(0, tex.index - 20), tex.index + 40));
}
const errors = [...document.querySelectorAll('mjx-merror, [data-mjx-error]')].map(
    el => el.getAttribute('data-mjx-error') || el.textContent.slice(0, 60));
const images = [...document.images].map(img => ({src: img.src.slice(0, 80), ok: img.complete && img.naturalWidth > 0}));
const resources = performance.getEntriesByType('resource').map(r => ({url: r.name, status: r.responseStatus}));
return {rendered, pending, errors, images, resources};
"""

_MATHJAX_DONE = """
const done = arguments[arguments.length - 1];
const start = Date.now();
(function wait() {
    if (window.MathJax && MathJax.startup && MathJax.startup.promise) {
        MathJax.startup.promise.then(() => done(true), () => done(false));
    } else if (Date.now() - start > 60000) {
        done(false);
    } else {
        setTimeout(wait, 100);
    }
})();
"""


def _serve(site: pathlib.Path) -> http.server.ThreadingHTTPServer:
    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(site)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


def _browser() -> webdriver.Chrome:
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if not chromium or not driver:
        raise SystemExit(
            "browser_check: needs Debian's chromium and chromium-driver (apt-get install chromium chromium-driver)"
        )
    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for flag in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1280,1600"):
        options.add_argument(flag)
    browser = webdriver.Chrome(service=Service(driver), options=options)
    browser.set_script_timeout(120)
    return browser


def check_page(browser, base: str, name: str, path: str) -> list[str]:
    """Open one page, wait for MathJax, and return what is wrong with it (empty: nothing)."""
    browser.get(f"{base}/{path}")
    WebDriverWait(browser, 60).until(lambda b: b.execute_script("return document.readyState") == "complete")
    if not browser.execute_async_script(_MATHJAX_DONE):
        return [f"{name}: MathJax did not load"]
    found = browser.execute_script(_INSPECT)
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    browser.save_screenshot(str(SCREENSHOTS / f"{name}.png"))
    problems = []
    if found["rendered"] < MIN_FORMULAS[name]:
        problems.append(f"{name}: {found['rendered']} formulas typeset (expected ≥ {MIN_FORMULAS[name]})")
    problems += [f"{name}: formula not typeset: {tex!r}" for tex in found["pending"]]
    problems += [f"{name}: MathJax error: {err!r}" for err in found["errors"]]
    if len(found["images"]) < MIN_IMAGES[name]:
        problems.append(f"{name}: {len(found['images'])} images (expected ≥ {MIN_IMAGES[name]})")
    problems += [f"{name}: image did not load: {img['src']}" for img in found["images"] if not img["ok"]]
    for resource in found["resources"]:
        if not resource["url"].startswith(base):
            problems.append(f"{name}: fetched from outside the site: {resource['url']}")
        elif resource["status"] and resource["status"] >= 400:
            problems.append(f"{name}: {resource['status']} for {resource['url']}")
    print(
        f"{name} ({path}): {found['rendered']} formulas typeset, "
        f"{sum(img['ok'] for img in found['images'])}/{len(found['images'])} images loaded"
    )
    return problems


def main(argv: list[str]) -> int:
    site = pathlib.Path(argv[0] if argv else ROOT / "site").resolve()
    if not (site / "index.html").exists():
        raise SystemExit(f"browser_check: no built site in {site} (run `mkdocs build` first)")
    server = _serve(site)
    base = f"http://127.0.0.1:{server.server_address[1]}"
    browser = _browser()
    try:
        problems = [p for name, path in PAGES.items() for p in check_page(browser, base, name, path)]
    finally:
        browser.quit()
        server.shutdown()
    for problem in problems:
        print("FAIL", problem)
    print(f"screenshots: {SCREENSHOTS.relative_to(ROOT)}/")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
