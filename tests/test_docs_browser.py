"""The documentation site in a real browser: headless Chromium (Debian's ``chromium`` and
``chromium-driver``) driven by Selenium over the built ``site/``, served on localhost.

Checks that every page loads without console errors, that the equations are rendered (MathML; no
raw ``$...$`` or ``\\(...\\)`` left in the visible text), that every public name has its anchor on
its API page, and takes screenshots of the home page and one API page (into
``$RBO_DOCS_SCREENSHOTS`` if set, else a pytest temporary folder).

Marked ``docs``: not part of ``make test``; ``make docs-test`` builds the site and runs it. The
site is ``$RBO_DOCS_SITE`` if set (built already), else ``site/``, built here first when it is
missing or older than ``docs/``, ``mkdocs.yml`` or the notebooks (a few minutes).
"""

from __future__ import annotations

import functools
import http.server
import json
import os
import re
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest

pytestmark = pytest.mark.docs

ROOT = Path(__file__).resolve().parent.parent
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"

# What is missing is said by each test (a skip there), not at import: a skip at import would show
# in every run that merely collects this file, `make test` included, where it is deselected.
MISSING = None
if not (Path(CHROMIUM).is_file() and Path(CHROMEDRIVER).is_file()):
    MISSING = (
        "no headless browser: install Debian's chromium and chromium-driver "
        "(apt-get install chromium chromium-driver)"
    )
try:
    import mkdocs  # noqa: F401
    import selenium  # noqa: F401
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By
except ImportError as error:
    MISSING = MISSING or f"the docs extra is not installed ({error.name}): pip install -e '.[docs]'"


@pytest.fixture(autouse=True, scope="module")
def _browser_and_docs_extra():
    if MISSING:
        pytest.skip(MISSING)


sys.path.insert(0, str(ROOT / "docs" / "_hooks"))
from api_names import public_names  # noqa: E402


def _newest(paths) -> float:
    return max(p.stat().st_mtime for top in paths for p in [top, *top.rglob("*")] if p.exists())


@pytest.fixture(scope="module")
def site() -> Path:
    given = os.environ.get("RBO_DOCS_SITE")
    path = Path(given) if given else ROOT / "site"
    if not path.is_absolute():
        path = ROOT / path
    sources = [ROOT / "docs", ROOT / "mkdocs.yml", ROOT / "notebooks"]
    if not given and (not (path / "index.html").is_file() or _newest([path]) < _newest(sources)):
        subprocess.run(
            [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(path)],
            cwd=ROOT,
            check=True,
        )
    assert (path / "index.html").is_file(), f"no built site in {path} (make docs)"
    return path


@pytest.fixture(scope="module")
def base_url(site):
    handler = functools.partial(_QuietHandler, directory=str(site))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}/"
    server.shutdown()
    server.server_close()


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    profile = tmp_path_factory.mktemp("chromium-profile")
    for arg in (
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--disable-dev-shm-usage",
        "--window-size=1280,1000",
        f"--user-data-dir={profile}",
    ):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    driver.set_page_load_timeout(60)
    yield driver
    driver.quit()


@pytest.fixture(scope="module")
def pages(site) -> list[str]:
    """Every page of the site, as a path relative to its root (``topics/kinematics/``)."""
    out = []
    for index in sorted(site.rglob("index.html")):
        rel = index.parent.relative_to(site).as_posix()
        out.append("" if rel == "." else rel + "/")
    assert len(out) > 20, out
    return out


@pytest.fixture(scope="module")
def visited(browser, base_url, pages):
    """Load each page once: its console's SEVERE entries, its visible text, its math count."""
    results = {}
    for page in pages:
        browser.get(base_url + page)
        severe = [e for e in browser.get_log("browser") if e["level"] == "SEVERE"]
        text = browser.execute_script(
            """
            const copy = document.body.cloneNode(true);  // the page, its navigation, its contents
            copy.querySelectorAll('pre, code, math, script, style').forEach(n => n.remove());
            return copy.textContent;
            """
        )
        math = len(browser.find_elements(By.CSS_SELECTOR, "article math"))
        resources = browser.execute_script(
            "return performance.getEntriesByType('resource').map(e => e.name)"
        )
        foreign = [url for url in resources if not url.startswith(base_url)]
        results[page] = {"severe": severe, "text": text, "math": math, "foreign": foreign}
    return results


def test_pages_load_without_console_errors(visited):
    errors = {page: r["severe"] for page, r in visited.items() if r["severe"]}
    assert not errors, json.dumps(errors, indent=1)[:4000]


def test_pages_load_nothing_from_the_network(visited):
    """No CDN: every script, style sheet, font and image comes from the site itself."""
    foreign = {page: r["foreign"] for page, r in visited.items() if r["foreign"]}
    assert not foreign, foreign


_RAW_MATH = re.compile(r"\$[^$\s][^$]*\$|\\\(|\\\)|\\\[|\\\]|\\frac|\\theta")


def test_equations_are_rendered(visited):
    raw = {}
    for page, r in visited.items():
        found = [m.group(0)[:60] for m in _RAW_MATH.finditer(r["text"])]
        if found:
            raw[page] = found[:5]
    assert not raw, f"raw LaTeX in the visible text: {raw}"
    for page in ("topics/kinematics/", "api/kinematics/", ""):
        assert visited[page]["math"] > 0, f"no MathML on {page or 'the home page'}"
    assert visited["api/kinematics/"]["math"] > 20


def test_math_is_laid_out(browser, base_url):
    """MathML is rendered by the browser: a display formula has a real size."""
    browser.get(base_url + "topics/kinematics/")
    box = browser.execute_script(
        "const m = document.querySelector('.math-display math');"
        "const r = m.getBoundingClientRect(); return [r.width, r.height];"
    )
    assert box[0] > 100 and box[1] > 15, box


def test_every_public_name_has_its_anchor(site, browser, base_url):
    manifest = json.loads((site / "api-names.json").read_text())
    expected = {f"{package}.{name}" for package, name in public_names()}
    assert expected <= set(manifest), sorted(expected - set(manifest))
    by_page: dict[str, list[dict]] = {}
    for public in sorted(expected):
        by_page.setdefault(manifest[public]["page"], []).append(manifest[public])
    missing = []
    for page, entries in by_page.items():
        browser.get(base_url + page)
        ids = set(
            browser.execute_script("return [...document.querySelectorAll('[id]')].map(e => e.id)")
        )
        for entry in entries:
            for anchor in (entry["anchor"], entry["entry"]):
                if anchor not in ids:
                    missing.append(f"{page}#{anchor}")
    assert not missing, missing


def test_screenshots(browser, base_url, tmp_path_factory):
    folder = os.environ.get("RBO_DOCS_SCREENSHOTS")
    out = Path(folder) if folder else tmp_path_factory.mktemp("screenshots")
    out.mkdir(parents=True, exist_ok=True)
    for name, page in (("home", ""), ("api-kinematics", "api/kinematics/")):
        browser.get(base_url + page)
        path = out / f"{name}.png"
        assert browser.save_screenshot(str(path)), path
        assert path.stat().st_size > 10_000, path
    print(f"screenshots in {out}")
