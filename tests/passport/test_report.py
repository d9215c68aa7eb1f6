"""The calibration certificate (issue 16, item 5): one HTML file that stands alone, checked for its content and
rendered in a real headless Chromium (Debian's package) with its figures decoded; printed to PDF by the same
browser."""

from __future__ import annotations

import base64
import io
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from flows.cli import main
from pipeline.passport.registry import Registry
from pipeline.passport.report import certificate_html, chromium, chromium_args

CHROMIUM = "/usr/bin/chromium"


@pytest.fixture(scope="module")
def certificate(calibrated_registry, tmp_path_factory, monkeypatch_module) -> dict:
    """``thermocal report UNIT 1 --registry R --out cert.html [--pdf cert.pdf] --json`` in this process."""
    out = tmp_path_factory.mktemp("cert") / "cert.html"
    args = [
        "report",
        calibrated_registry["unit"],
        "1",
        "--registry",
        str(calibrated_registry["registry"]),
        "--out",
        str(out),
        "--json",
    ]
    if Path(CHROMIUM).exists():
        args += ["--pdf", str(out.with_suffix(".pdf"))]
    monkeypatch_module.setattr(sys, "argv", ["thermocal", *args])
    buf = io.StringIO()
    monkeypatch_module.setattr(sys, "stdout", buf)
    with pytest.raises(SystemExit) as info:
        main()
    monkeypatch_module.undo()
    assert info.value.code == 0
    return {
        "result": json.loads(buf.getvalue()),
        "path": out,
        "doc": Registry(calibrated_registry["registry"]).load(calibrated_registry["unit"], 1),
    }


@pytest.fixture(scope="module")
def monkeypatch_module():
    mp = pytest.MonkeyPatch()
    yield mp
    mp.undo()


def test_certificate_states_what_a_signer_needs(certificate):
    page = certificate["path"].read_text()
    doc = certificate["doc"]
    res = certificate["result"]
    assert res["certificate"] == str(certificate["path"]) and res["version"] == 1
    assert res["valid_temp_c"] == doc["valid_temp_c"] and res["status"] == doc["status"]
    for text in (
        doc["unit"],
        doc["content_sha256"],
        doc["signature"]["key_id"],
        doc["method"],
        "polynomial, order",
        f"{doc['valid_temp_c'][0]:+.1f} C to {doc['valid_temp_c'][1]:+.1f} C",
        f"status: {doc['status'].upper()}",
        "not approved",
        "calibrated by",
        "checked and approved by",
    ):
        assert text in page, text
    for inp in doc["provenance"]["inputs"]:
        assert inp["sha256"] in page and inp["path"] in page
    # the constants at T0 with their uncertainty, as the passport has them
    k_xx, s_xx = doc["coefficients"]["K"][0][0], doc["uncertainty"]["coefficients"]["K"][0][0]
    assert f"{k_xx:+.8f} &plusmn; {s_xx * 1e6 / abs(k_xx):.2g} ppm" in page
    # a thermal coefficient in engineering units: value +- its uncertainty, then the unit
    b1, sb1 = doc["thermal_model"]["beta"]["xx"][0], doc["uncertainty"]["thermal_model"]["beta"]["xx"][0]
    assert f"{b1 * 1e6:+.4g} &plusmn; {sb1 * 1e6:.2g} ppm/C^1<" in page
    # every verification row, against its limit
    vp_rows = re.findall(
        r"<tr class='(?:failrow)?'><td>([+-]\d+\.\d\d) C.*?</td><td>(VP\d)</td>"
        r"(?:<td class='num'>[^<]*</td>){3}<td class='num'>(\d+)</td>",
        page,
    )
    assert len(vp_rows) == len(doc["verification"])
    assert {(p, lim) for _, p, lim in vp_rows} == {
        (r["position"], f"{r['tolerance_g'] * 1e6:.0f}") for r in doc["verification"]
    }
    # the figures are inside the file: two PNGs that decode
    uris = re.findall(r"src='data:image/png;base64,([A-Za-z0-9+/=]+)'", page)
    assert len(uris) == 2
    sizes = [Image.open(io.BytesIO(base64.b64decode(u))).size for u in uris]
    assert all(w > 500 and h > 300 for w, h in sizes)
    assert "src='http" not in page and "<script" not in page


def test_approval_and_failing_rows_show(calibrated_registry):
    doc = Registry(calibrated_registry["registry"]).load(calibrated_registry["unit"], 1)
    doc = json.loads(json.dumps(doc))
    doc["verification"][0].update(dg_method1_g=2e-3, passed=False)
    page = certificate_html(doc, approved=[{"by": "J. Doe", "approved_utc": "2026-11-22T10:00:00Z"}], figures={})
    assert "approved by J. Doe at 2026-11-22T10:00:00Z" in page
    assert page.count("class='failrow'") == 1 and ">FAIL<" in page


def _probe(page: Path) -> Path:
    """A copy of the certificate with a script that, once the page has loaded, writes every image's natural size
    into the body's ``data-images`` attribute (the certificate itself has no script)."""
    probe = page.with_name("probe.html")
    script = (
        "<script>window.addEventListener('load', () => { document.body.setAttribute('data-images', "
        "JSON.stringify([...document.images].map(i => [i.complete, i.naturalWidth, i.naturalHeight]))); "
        "});</script>"
    )
    probe.write_text(page.read_text().replace("</body>", script + "</body>"))
    return probe


@pytest.mark.skipif(
    not Path(CHROMIUM).exists(),
    reason="Chromium is not installed (apt-get install chromium): the certificate is not rendered in a browser",
)
@pytest.mark.slow  # a headless browser
def test_chromium_renders_the_certificate_with_its_figures(certificate):
    assert chromium() is not None
    probe = _probe(certificate["path"])
    with tempfile.TemporaryDirectory() as profile:
        dom = subprocess.run(
            [CHROMIUM, *chromium_args(profile), "--virtual-time-budget=10000", "--dump-dom", probe.as_uri()],
            capture_output=True,
            text=True,
            timeout=180,
        )
    assert dom.returncode == 0, dom.stderr[-2000:]
    m = re.search(r'data-images="([^"]*)"', dom.stdout)
    assert m, dom.stdout[:500]
    images = json.loads(m.group(1).replace("&quot;", '"'))
    assert len(images) == 2 and all(done and w > 500 and h > 300 for done, w, h in images), images
    shot = certificate["path"].with_name("shot.png")
    with tempfile.TemporaryDirectory() as profile:
        subprocess.run(
            [
                CHROMIUM,
                *chromium_args(profile),
                "--window-size=1000,4200",
                "--hide-scrollbars",
                f"--screenshot={shot}",
                certificate["path"].as_uri(),
            ],
            capture_output=True,
            timeout=180,
        )
    img = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    blue = np.all(np.abs(img - [0x1F, 0x77, 0xB4]) < 30, axis=-1)  # the figures' series, as drawn
    green = np.all(np.abs(img - [0x17, 0x63, 0x17]) < 30, axis=-1)  # the PASS badge and verdicts
    assert blue.sum() > 1000, "no figure pixels in the rendered page"
    assert (green.sum() > 50) == (certificate["doc"]["status"] == "pass")
    pdf = certificate["path"].with_suffix(".pdf")
    assert certificate["result"]["pdf"] == str(pdf)
    assert pdf.read_bytes()[:5] == b"%PDF-" and pdf.stat().st_size > 100_000  # the figures are in it
