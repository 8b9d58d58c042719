"""``make qc-screenshots``: a PASS and a FAIL QC report rendered by headless Chromium
into out/screenshots/ (qc-report-pass.png, qc-report-fail.png), plus the control chart
of a small batch (qc-chart-damping.png), so that a person can look at what the station
shows.  The units are simulated (a good one and one with a worn orifice), judged with
the default spec through the public command line: their reports carry the SIMULATED
watermark, and the chart counts them with --include-simulated.  The FAIL report is also
printed to PDF as a browser prints it (A4) and each page rasterised
(qc-report-fail-print-N.png, with poppler's pdftoppm): the running head, the page
numbers and the watermark on every page, no machine path.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from matplotlib import image

CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--hide-scrollbars"]

TALL_PX = 12000           # taller than any report
DARK = 0.78               # brightness below which a pixel is content (text, plots), not the pale watermark
BOTTOM_MARGIN_PX = 32


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=600)


def screenshot(chromium: str, page: Path, png: Path, width: int, height: int, profile: Path) -> None:
    r = subprocess.run([chromium, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--screenshot={png}",
                        f"--window-size={width},{height}", page.as_uri()], capture_output=True, text=True, timeout=180)
    if r.returncode != 0 or not png.is_file():
        raise SystemExit(f"chromium failed on {page} (exit {r.returncode}): {r.stderr[-2000:]}")


def full_page(chromium: str, page: Path, png: Path, width: int, profile: Path) -> None:
    """The whole page, however long: headless Chromium's --screenshot takes the window only,
    so a first shot in a window taller than any report finds where the content ends (the
    last row with dark pixels; the pale watermark is not content), and the second is taken
    at that height so the fixed watermark sits where a reader's window would put it."""
    screenshot(chromium, page, png, width, TALL_PX, profile)
    rgb = image.imread(png)[:, :, :3]          # matplotlib reads PNG natively (a project dependency)
    rows = (rgb.max(axis=2) < DARK).any(axis=1).nonzero()[0]
    if rows.size == 0 or rows[-1] >= TALL_PX - 1:
        raise SystemExit(f"{page}: the page is empty or longer than {TALL_PX} px")
    screenshot(chromium, page, png, width, int(rows[-1]) + BOTTOM_MARGIN_PX, profile)


def printed(chromium: str, page: Path, out: Path, stem: str, profile: Path) -> list[Path]:
    """The report printed to PDF (no browser header or footer: those would show the file's
    path; the report's own @page margins carry its head and page numbers), each page as a PNG."""
    pdf = out / f"{stem}.pdf"
    r = subprocess.run([chromium, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "--no-pdf-header-footer",
                        f"--print-to-pdf={pdf}", page.as_uri()], capture_output=True, text=True, timeout=180)
    if r.returncode != 0 or not pdf.is_file():
        raise SystemExit(f"chromium could not print {page} (exit {r.returncode}): {r.stderr[-2000:]}")
    pdftoppm = shutil.which("pdftoppm")
    if not pdftoppm:
        print(f"{pdf} (pdftoppm not installed: apt-get install poppler-utils for its pages as PNG)", file=sys.stderr)
        return [pdf]
    for old in out.glob(f"{stem}-*.png"):
        old.unlink()
    subprocess.run([pdftoppm, "-r", "70", "-png", str(pdf), str(out / stem)], check=True, timeout=120)
    return [pdf, *sorted(out.glob(f"{stem}-*.png"))]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="out/screenshots")
    args = parser.parse_args()
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if not chromium:
        raise SystemExit("chromium is not installed (apt-get install -y chromium)")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        db = tmp / "records.sqlite"
        reports = {}
        for verdict, unit, seed in (("pass", "good", 4), ("fail", "worn-orifice", 2)):
            data = tmp / unit
            r = run("-m", "simulator", "generate", "--plan", "rig/qc/specs/default.toml", "--unit", unit,
                    "--unit-seed", str(seed), "--seed", str(seed), "--serial", f"SN-{4200 + seed}", "--out", str(data))
            if r.returncode != 0:
                raise SystemExit(r.stderr)
            r = run("-m", "rig", "qc", "judge", str(data), "--db", str(db), "--create-db", "--operator", "screenshots")
            if r.returncode not in (0, 1):
                raise SystemExit(r.stderr)
            (reports[verdict],) = data.glob("qc-report-*.html")
        for seed in range(5, 13):       # a small batch for the control chart
            data = tmp / f"batch-{seed}"
            run("-m", "simulator", "generate", "--plan", "rig/qc/specs/default.toml", "--unit", "good", "--unit-seed",
                str(seed), "--seed", str(seed), "--serial", f"SN-{4200 + seed}", "--out", str(data))
            run("-m", "rig", "qc", "judge", str(data), "--db", str(db), "--operator", "screenshots")
        r = run("-m", "rig", "qc", "history", "--db", str(db), "--include-simulated", "--chart", str(tmp / "charts"))
        if r.returncode != 0:
            raise SystemExit(r.stderr)
        shutil.copy(tmp / "charts" / "damping_force_0.3_N.png", out / "qc-chart-damping.png")
        for verdict, page in reports.items():
            full_page(chromium, page, out / f"qc-report-{verdict}.png", 1100, tmp / "chromium")
        pages = printed(chromium, reports["fail"], out, "qc-report-fail-print", tmp / "chromium")
    for name in ("qc-report-pass.png", "qc-report-fail.png", "qc-chart-damping.png"):
        print(out / name)
    for path in pages:
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
