"""The HTML report in a real headless browser (Debian's chromium): it loads from its folder with no
console error, the interactive 3D view draws (and redraws when asked), every image resolves, and
the headline table is on the first screen. Screenshots are kept in ``test-artifacts/`` (ignored
by git; the paths are printed).

Skipped with the reason when chromium is missing, except in CI (``CI`` set), where
``scripts/install-system-deps.sh`` installs it and a missing browser fails.
"""

import io
import json
import os
from pathlib import Path

import numpy as np
import pytest

from _browser import HeadlessChromium, chromium_executable
from _surrogate_synthetic import FakeDataset

ARTIFACTS = Path(__file__).resolve().parents[2] / "test-artifacts"
VIEWER = "document.getElementById('tc-viewer')"


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    exe = chromium_executable()
    if exe is None:
        if os.environ.get("CI"):
            pytest.fail("chromium is missing in CI: scripts/install-system-deps.sh installs it (apt-get install chromium)")
        pytest.skip("chromium is not installed (Debian: apt-get install chromium); CI installs it and runs this test")
    b = HeadlessChromium(exe, tmp_path_factory.mktemp("chromium-profile"))
    yield b
    b.close()


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    from tissuecast.evaluate.evaluation import evaluate_model
    from tissuecast.evaluate.report import write_report
    from tissuecast.surrogate import DeformationModel

    ds = FakeDataset()
    model = DeformationModel.from_dataset(ds, epochs=40, patience=0, n_components=8, ensemble=2, head="none",
                                          learning_rate=3e-3, batch_size=64)
    evaluation = evaluate_model(model, ds)
    return write_report(tmp_path_factory.mktemp("report"), model, ds, evaluation, renders=1)


def _pixels(path: Path) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(path.read_bytes())).convert("RGB"), dtype=np.float64)


def test_the_harness_sees_console_errors_exceptions_and_missing_images(browser, tmp_path):
    page = tmp_path / "broken.html"
    page.write_text("<!DOCTYPE html><html><body><img src='missing.png'><script>console.error('boom');"
                    "undefinedFunction();</script></body></html>")
    browser.errors.clear()
    browser.navigate(page.as_uri())
    text = " | ".join(browser.errors)
    assert "console: boom" in text and "undefinedFunction" in text and "missing.png" in text
    assert browser.evaluate("document.images[0].naturalWidth") == 0


def test_report_loads_draws_and_resolves_every_image(browser, report):
    ARTIFACTS.mkdir(exist_ok=True)
    browser.errors.clear()
    browser.navigate(report.as_uri())
    assert browser.wait_until(f"{VIEWER}.getAttribute('data-drawn')", timeout=30) == "true"
    images = json.loads(browser.evaluate(
        "JSON.stringify(Array.from(document.images).map(i => [i.getAttribute('src'), i.complete, i.naturalWidth]))"))
    assert len(images) == report.read_text().count("<img ") >= 4
    assert all(complete and width > 0 for _, complete, width in images), images
    # the first screen answers how good, against what, how sure
    assert browser.evaluate("document.querySelector('table.tc-headline').getBoundingClientRect().bottom <= innerHeight")
    assert browser.evaluate("document.querySelector('table.tc-sure').getBoundingClientRect().bottom <= innerHeight")
    first = browser.screenshot(ARTIFACTS / "report_first_screen.png")
    print(f"\nscreenshot of the report's first screen: {first}")
    rect = json.loads(browser.evaluate("JSON.stringify(document.querySelector('canvas.tc-canvas').getBoundingClientRect())"))
    clip = {"x": rect["x"] + window_scroll(browser, "X"), "y": rect["y"] + window_scroll(browser, "Y"),
            "width": rect["width"], "height": rect["height"]}
    shot = browser.screenshot(ARTIFACTS / "report_3d_view.png", clip=clip)
    print(f"screenshot of the 3D view: {shot}")
    px = _pixels(shot)
    half = px.shape[1] // 2
    for side in (px[:, :half], px[:, half:]):
        drawn = np.any(np.abs(side - 255.0) > 30, axis=2)
        assert drawn.mean() > 0.05 and side.std() > 20  # a coloured surface, not a blank canvas
    # asking for rigid registration redraws the right panel with its (larger, other) errors
    browser.evaluate(f"(() => {{ const s = {VIEWER}.querySelector('[data-control=method]'); s.value = 'rigid';"
                     "s.dispatchEvent(new Event('change')); })()")
    assert browser.wait_until(f"{VIEWER}.querySelector('[data-control=title-right]').textContent"
                              ".startsWith('rigid registration')")
    browser.wait_until("new Promise(r => requestAnimationFrame(() => requestAnimationFrame(() => r(true))))")
    after = _pixels(browser.screenshot(ARTIFACTS / "report_3d_view_rigid.png", clip=clip))
    assert np.abs(after[:, half:] - px[:, half:]).mean() > 1.0 and np.abs(after[:, :half] - px[:, :half]).mean() < 1.0
    assert browser.errors == []


def window_scroll(browser, axis: str) -> float:
    return float(browser.evaluate(f"window.scroll{axis}"))


def test_without_the_3d_view_the_report_opens_its_static_renders(browser, report, tmp_path):
    """Where the viewer cannot draw (here: its data did not load; elsewhere: no WebGL) the page
    shows no empty frame or dead controls, opens the static renders and says so."""
    import shutil

    folder = tmp_path / "report"
    shutil.copytree(report.parent, folder)
    (folder / "viewer_data.js").write_text("// lost\n")
    browser.errors.clear()
    browser.navigate((folder / report.name).as_uri())
    assert browser.wait_until(f"{VIEWER}.getAttribute('data-drawn')", timeout=30) == "error"
    for name in ("tc-canvas", "tc-controls", "tc-panels"):
        assert browser.evaluate(f"getComputedStyle({VIEWER}.querySelector('.{name}')).display") == "none", name
    assert browser.evaluate("document.getElementById('tc-renders').open") is True
    message = browser.evaluate(f"{VIEWER}.querySelector('.tc-message').textContent")
    assert message.startswith("The 3D view cannot be shown here (viewer_data.js did not load). The static renders, "
                              "opened below")
    assert any("viewer_data.js did not load" in e for e in browser.errors)  # the error itself stays visible in the console
    browser.errors.clear()
