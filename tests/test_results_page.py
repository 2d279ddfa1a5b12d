"""``benchmarks/results_page.py``: docs/results.md is what the committed results files give, and a changed number in
a results file makes the check fail (the page cannot drift from the files)."""

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "results_page.py"


def page(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, cwd=ROOT, timeout=60)


def test_the_committed_page_is_what_the_results_files_give():
    run = page("--check")
    assert run.returncode == 0, run.stderr
    lines = (ROOT / "docs" / "results.md").read_text().splitlines()
    cells = [cell for line in lines if line.startswith("|") for cell in line.strip("|").split("|")]
    assert len(lines) <= 150 and max(len(cell.strip()) for cell in cells) <= 200  # the page's size goals


def test_a_changed_result_fails_the_check_and_regenerates_the_row(tmp_path):
    results = tmp_path / "results"
    shutil.copytree(ROOT / "benchmarks" / "results", results, ignore=shutil.ignore_patterns("*.png"))
    committed = (ROOT / "docs" / "results.md").read_text()
    path = results / "mw_proxy.json"
    data = json.loads(path.read_text())
    data["cso_minus_il"] = {"mean": 0.1, "ci95": [-0.02, 0.22], "seeds": data["cso_minus_il"]["seeds"]}
    path.write_text(json.dumps(data))

    run = page("--check", f"--results_dir={results}")
    assert run.returncode == 1
    assert run.stderr.strip().splitlines() == [
        f"error: {ROOT / 'docs' / 'results.md'} differs from the results files; run python benchmarks/results_page.py"
    ]
    out = tmp_path / "results.md"
    assert page(f"--results_dir={results}", f"--page={out}").returncode == 0
    row = next(line for line in out.read_text().splitlines() if line.startswith("| MW-proxy: CSO − IL ≥ +15"))
    assert "| +10.0 [−2.0, +22.0], 5 seeds | **missed** on the mean;" in row
    assert "| +17.8 [+10.2, +25.4], 5 seeds | **met** on the mean;" in committed
    assert (ROOT / "docs" / "results.md").read_text() == committed  # the check wrote nothing


def test_a_missing_results_file_is_one_error_line(tmp_path):
    (tmp_path / "results").mkdir()
    run = page("--check", f"--results_dir={tmp_path / 'results'}")
    assert run.returncode != 0
    assert run.stderr.strip().splitlines()[-1].startswith("error: no results file ")


def test_the_readmes_results_table_is_read_from_the_page():
    """Every number in the README's results table (its IL → R-SFT → CSO and CSO − IL columns) is on docs/results.md,
    and every results file it links exists."""
    section = (ROOT / "README.md").read_text().split("\n## Results\n", 1)[1].split("\n## ", 1)[0]
    rows = [line.strip("|").split("|") for line in section.splitlines() if line.startswith("| ") and "---" not in line]
    on_page = set(re.findall(r"[+−]?\d+\.?\d*", (ROOT / "docs" / "results.md").read_text()))
    assert len(rows) >= 5
    for _, rates, gain, link in rows[1:]:
        assert set(re.findall(r"[+−]?\d+\.?\d*", rates + gain)) <= on_page, (rates, gain)
        assert (ROOT / re.search(r"\((benchmarks/results/[\w.]+)\)", link)[1]).is_file()


def test_a_gain_of_one_seed_is_shown_without_a_verdict(tmp_path):
    """A benchmark with one training seed so far (LIBERO-Object) has no interval over seeds: its CSO − IL row gives
    the seed's difference and waits for more seeds instead of judging the goal."""
    results = tmp_path / "results"
    shutil.copytree(ROOT / "benchmarks" / "results", results, ignore=shutil.ignore_patterns("*.png"))
    path = results / "libero_object.json"
    data = json.loads(path.read_text())
    data["methods"]["cso"]["per_seed"] = {"0": 0.25}
    data["cso_minus_il"] = {"mean": 0.25, "ci95": None, "seeds": ["0"]}
    path.write_text(json.dumps(data))
    out = tmp_path / "results.md"
    run = page(f"--results_dir={results}", f"--page={out}", f"--plot={tmp_path / 'plot.png'}")
    assert run.returncode == 0, run.stderr
    row = next(line for line in out.read_text().splitlines() if line.startswith("| CSO − IL ≥ +10 points, CI above 0"))
    assert "| +25.0, seed 0 only | not shown yet (1 seed) |" in row
