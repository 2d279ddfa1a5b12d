"""docs/results.md from the committed results files: one row per benchmark goal, every number read from a file.

    python benchmarks/results_page.py            # writes docs/results.md and docs/img/results.png
    python benchmarks/results_page.py --check    # exit 1 when docs/results.md is not what the files give

Success rates are % on held-out initial states. Over training seeds, ± is the standard deviation across seeds and
[a, b] the 95 % Student-t interval of the paired difference that the benchmark stored; on the twin, [a, b] is the
95 % interval over paired trials that ``twin_table5.py`` stored. A goal is met or missed on the stored numbers
alone; nothing is rounded before it is compared.
"""

import argparse
import json
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
Results = dict[str, Any]


@dataclass(frozen=True)
class Row:
    """One goal: what is measured and the goal, the results file it is read from, and how."""

    goal: str
    files: tuple[str, ...]
    read: Callable[..., tuple[str, str]]  # each file's contents, in order -> (result with its noise, met / missed)


def num(x: float, signed: bool = False, digits: int = 1) -> str:
    """A number as the page prints it: fixed digits, a real minus sign."""
    return (f"{x:+.{digits}f}" if signed else f"{x:.{digits}f}").replace("-", "−")


def pct(x: float) -> str:
    return num(100 * x)


def sr(r: Results, method: str) -> str:
    """A method's mean success over seeds ± the std across them."""
    m = r["methods"][method]
    return f"{pct(m['mean'])} ± {pct(m['std'])}"


def diff(d: dict[str, Any]) -> str:
    """A stored paired difference: mean [95 % CI], in points."""
    lo, hi = d["ci95"]
    return f"{num(100 * d['mean'], True)} [{num(100 * lo, True)}, {num(100 * hi, True)}]"


def per_seed(r: Results, a: str, b: str) -> dict[str, float]:
    """SR(a) − SR(b) per training seed that both ran."""
    pa, pb = r["methods"][a]["per_seed"], r["methods"][b]["per_seed"]
    return {s: pa[s] - pb[s] for s in sorted(pa.keys() & pb.keys(), key=int)}


def verdict(ok: bool, short_by: float | None = None) -> str:
    return "**met**" if ok else "**missed**" if short_by is None else f"**missed** by {num(short_by)}"


def at_least(r: Results, key: str, goal: float) -> tuple[str, str]:
    """A stored difference against a goal in points, with the lower end of its CI."""
    d = r[key]
    return diff(d), verdict(d["mean"] >= goal, 100 * (goal - d["mean"]))


def seeds_at_least(r: Results, a: str, b: str, goal: float) -> tuple[int, int, str]:
    """How many seeds reach ``goal`` for SR(a) − SR(b), of how many, and the ones that do not."""
    d = per_seed(r, a, b)
    short = [f"seed {s}: {num(100 * v, True)}" for s, v in d.items() if v < goal]
    return len(d) - len(short), len(d), ", ".join(short)


def gain(goal: float, key: str = "cso_minus_il", a: str = "cso", b: str = "il", ci: bool = False) -> Callable:
    def read(r: Results) -> tuple[str, str]:
        d = r[key]
        if d["ci95"] is None:  # one seed so far: no interval, and no verdict on a goal over seeds
            return f"{num(100 * d['mean'], True)}, seed {d['seeds'][0]} only", "not shown yet (1 seed)"
        ok_mean = d["mean"] >= goal and (not ci or d["ci95"][0] > 0)
        k, n, short = seeds_at_least(r, a, b, goal)
        seeds = f"{k} of {n} seeds" + (f" ({short})" if short else "")
        return f"{diff(d)}, {len(d['seeds'])} seeds", f"{verdict(ok_mean)} on the mean; {seeds}"

    return read


def stages(r: Results) -> tuple[str, str]:
    return f"IL {sr(r, 'il')} → R-SFT {sr(r, 'rsft')} → CSO {sr(r, 'cso')}", "—"


def not_below(a: str, b: str) -> Callable:
    """SR(a) ≥ SR(b): both means and the seeds where it holds."""

    def read(r: Results) -> tuple[str, str]:
        k, n, short = seeds_at_least(r, a, b, 0.0)
        mean = r["methods"][a]["mean"] - r["methods"][b]["mean"]
        text = f"{name(a)} {sr(r, a)}, {name(b)} {sr(r, b)}: {num(100 * mean, True)}"
        return text, f"{verdict(mean >= 0)} on the mean; {k} of {n} seeds" + (f" ({short})" if short else "")

    return read


def name(method: str) -> str:
    return {"il": "IL", "rsft": "R-SFT", "cso": "CSO", "spo_only": "SPO only", "cso_no_freeze": "no freeze",
            "token": "token", "trajectory": "trajectory", "ript": "RIPT"}[method]  # fmt: skip


def clip_order(r: Results) -> tuple[str, str]:
    """The paper's order of the clip fractions: trajectory > skill > token and RIPT."""
    c = {m: r["methods"][m]["clip_fraction"] for m in ("trajectory", "cso", "token", "ript")}
    text = ", ".join(f"{'skill' if m == 'cso' else name(m)} {num(v, digits=2)}" for m, v in c.items())
    return text, verdict(c["trajectory"] > c["cso"] > max(c["token"], c["ript"]))


def at_least_sr(method: str, goal: float) -> Callable:
    def read(r: Results) -> tuple[str, str]:
        mean = r["methods"][method]["mean"]
        return sr(r, method), verdict(mean >= goal, 100 * (goal - mean))

    return read


def gap_closed(r: Results) -> tuple[str, str]:
    return f"{pct(r['gap_closed'])} % of IL's gap to 100 %", verdict(r["gap_closed"] >= 0.5)


def three_seeds_time(r: Results) -> tuple[str, str]:
    """Three seeds' wall time, from the seeds whose pipeline ran from scratch in the file's runs (a resumed pipeline
    records its few seconds of skipping)."""
    fresh = {s: sum(t.values()) for s, t in r["seconds"].items() if t.get("pipeline", 0) > 60}
    mins = sorted(3 * v / 60 for v in fresh.values())
    text = f"{num(mins[0], digits=0)}–{num(mins[-1], digits=0)} min for 3 seeds (from {len(mins)} seeds run whole)"
    return text, verdict(mins[0] <= 180)


def camera_costs(r: Results) -> tuple[str, str]:
    (camera, state) = r["throughput"]
    steps = r["cost_split_seconds"][camera]["per_env_step"]
    total = sum(steps.values())
    parts = ", ".join(f"{k} {100 * v / total:.0f} %" for k, v in steps.items() if k in ("render", "sim"))
    text = (
        f"camera {r['throughput'][camera]['env_steps_per_s']:.0f} env steps/s, state "
        f"{r['throughput'][state]['env_steps_per_s']:.0f}; a camera env step {1000 * total:.2f} ms ({parts})"
    )
    return text, "— (no goal)"


def twin_task(task: str) -> Callable:
    def read(r: Results) -> tuple[str, str]:
        t = r["tasks"][task]
        p = t["paired"]["cso_minus_il"]
        s = " → ".join(f"{name(k)} {100 * t['sr'][k]:.0f} %" for k in ("il", "rsft", "cso"))
        return f"{s}; CSO − IL {diff(p)}, {p['trials']} paired trials", "—"

    return read


def twin_mean(press: Results, cube: Results) -> tuple[str, str]:
    """Table 5's goal: CSO − IL on the mean of Press Button and Cube in Bowl."""
    gains = [press["tasks"]["press_button"]["cso_minus_il"], cube["tasks"]["cube_in_bowl"]["cso_minus_il"]]
    mean = sum(gains) / 2
    text = f"{num(100 * mean, True)} (press {num(100 * gains[0], True)}, cube {num(100 * gains[1], True)})"
    return text, verdict(mean >= 0.15, 100 * (0.15 - mean))


def evaluated_sr(r: Results, method: str) -> str:
    """A method's success: over several training seeds as :func:`sr`; of one seed, ± one binomial standard error
    over its evaluation episodes (per task × tasks × evaluation seeds, from the file's config)."""
    values = r["methods"][method]["per_seed"]
    if len(values) > 1:
        return f"{sr(r, method)} ({len(values)} seeds)"
    (seed, p), cfg = next(iter(values.items())), r["config"]
    n = cfg["eval"]["episodes_per_task"] * len(cfg["tasks"].split(",")) * len(str(cfg["eval"]["seeds"]).split(","))
    return f"{pct(p)} ± {pct((p * (1 - p) / n) ** 0.5)} (seed {seed}, {n} episodes)"


def when_run(method: str, read: Callable) -> Callable:
    """``read`` once ``method`` has a result in the file; until then the row says so."""

    def guarded(r: Results) -> tuple[str, str]:
        if not r["methods"][method]["per_seed"]:
            return "not run yet", "—"
        return read(r)

    return guarded


def pixel_il(goal: float) -> Callable:
    def read(r: Results) -> tuple[str, str]:
        mean = r["methods"]["il"]["mean"]
        return evaluated_sr(r, "il"), verdict(mean >= goal, 100 * (goal - mean))

    return read


def episodes_paired(a: str, b: str) -> Callable:
    """SR(a) − SR(b) of each training seed over the evaluation episodes both ran from the same initial states, with
    its 95 % CI: the evaluation's noise alone, for results of too few seeds for a CI over seeds."""

    def read(r: Results) -> tuple[str, str]:
        per_seed = r[f"{a}_minus_{b}_per_seed_episodes"]
        parts = [f"seed {s}: {diff(d)} over {d['episodes']} paired episodes" for s, d in per_seed.items()]
        return f"{name(a)} {evaluated_sr(r, a)}; {name(a)} − {name(b)}, {'; '.join(parts)}", "—"

    return read


def expert_success(r: Results) -> tuple[str, str]:
    """LIBERO-Object's scripted expert: ≥ 90 % on every task, on ≥ 50 training placements each."""
    rows = r["tasks"]
    placements = min(t["episodes"] for t in rows.values())
    low = min(rows, key=lambda task: rows[task]["rate"])
    counts = sorted({t["episodes"] for t in rows.values()}, reverse=True)
    parts = []
    for n in counts:  # the tasks run at each number of placements
        group = [t for t in rows.values() if t["episodes"] == n]
        parts.append(f"{len(group)} tasks × {n}: {sum(t['successes'] for t in group)}/{n * len(group)}")
    text = f"{'; '.join(parts)}; the lowest {pct(rows[low]['rate'])} ± {pct(rows[low]['se'])} % ({low})"
    if placements < 50 or len(rows) < 10:
        full = sum(t["episodes"] >= 50 for t in rows.values())
        return text, f"not shown yet ({full} of 10 tasks at 50 placements)"
    return text, verdict(all(t["rate"] >= 0.9 for t in rows.values()))


SECTIONS: dict[str, list[Row]] = {
    "MetaWorld, state observation (the demo's three tasks)": [
        Row("Demo config (`configs/metaworld_demo.yaml`): IL → R-SFT → CSO", ("mw_proxy_demo.json",), stages),
        Row("Demo config: CSO − IL ≥ +10 points", ("mw_proxy_demo.json",), gain(0.10)),
        Row(
            "Demo config: R-SFT − IL ≥ +5 points", ("mw_proxy_demo.json",), lambda r: at_least(r, "rsft_minus_il", 0.05)
        ),
        Row("MW-proxy (`configs/mw_proxy.yaml`): IL → R-SFT → CSO", ("mw_proxy.json",), stages),
        Row("MW-proxy: CSO − IL ≥ +15 points, CI above 0", ("mw_proxy.json",), gain(0.15, ci=True)),
        Row("MW-proxy: R-SFT − IL ≥ +5 points", ("mw_proxy.json",), gain(0.05, "rsft_minus_il", "rsft")),
        Row("MW-proxy: CSO ≥ R-SFT only", ("mw_proxy.json",), not_below("cso", "rsft")),
        Row("MW-proxy: CSO ≥ SPO only (from IL)", ("mw_proxy.json",), not_below("cso", "spo_only")),
        Row("MW-proxy: skill ratio (CSO) ≥ token (GRPO)", ("mw_proxy.json",), not_below("cso", "token")),
        Row("MW-proxy: skill ratio ≥ trajectory (GSPO)", ("mw_proxy.json",), not_below("cso", "trajectory")),
        Row("MW-proxy: skill ratio ≥ RIPT", ("mw_proxy.json",), not_below("cso", "ript")),
        Row("MW-proxy: clip fractions ordered as in the paper", ("mw_proxy.json",), clip_order),
    ],
    "MetaWorld, camera observation (QueST's: `corner2` 64² + 8-d proprio)": [
        Row("Camera benchmark (`configs/metaworld_vision.yaml`): IL → R-SFT → CSO", ("mw_vision.json",), stages),
        Row("Camera: pixel IL ≥ 40 %", ("mw_vision.json",), at_least_sr("il", 0.40)),
        Row("Camera: CSO − IL ≥ +15 points, CI above 0, ≥ 3 seeds", ("mw_vision.json",), gain(0.15, ci=True)),
        Row("Camera: R-SFT − IL ≥ +5 points", ("mw_vision.json",), gain(0.05, "rsft_minus_il", "rsft")),
        Row("Camera: CSO closes ≥ 50 % of IL's gap", ("mw_vision.json",), gap_closed),
        Row("Camera: CSO ≥ SPO only (from IL)", ("mw_vision.json",), not_below("cso", "spo_only")),
        Row("Camera: CSO ≥ CSO without the encoder freeze", ("mw_vision.json",), not_below("cso", "cso_no_freeze")),
        Row("Camera: three seeds ≤ 3 h on 2 cores", ("mw_vision.json",), three_seeds_time),
        Row("Camera rollouts: what a camera costs (`rollout_costs.py`)", ("rollout_costs.json",), camera_costs),
    ],
    "PiPER physics twin, Table 5's protocol (`twin_table5.py`)": [
        Row("Press Button (6 SPO iterations)", ("twin_table5_dm_press_t100.json",), twin_task("press_button")),
        Row("Press Button (12 SPO iterations)", ("twin_table5_spo12_press_t100.json",), twin_task("press_button")),
        Row(
            "Cube in Bowl (demos that retry a missed grasp)",
            ("twin_table5_regrasp_cube.json",),
            twin_task("cube_in_bowl"),
        ),
        Row(
            "Table 5: CSO − IL ≥ +15 points on the mean of the two tasks (100 trials)",
            ("twin_table5_dm_press_t100.json", "twin_table5_regrasp_cube.json"),
            twin_mean,
        ),
    ],
    "LIBERO-Object, offline (the paper's main benchmark)": [
        Row(
            "Scripted expert ≥ 90 % on every task, 50 training placements each", ("libero_expert.json",), expert_success
        ),
        Row(
            "Pixel IL ≥ 50 % (`configs/libero_object.yaml`: tasks 0-2, 50 fixed init states each)",
            ("libero_object.json",),
            when_run("il", pixel_il(0.50)),
        ),
        Row(
            "R-SFT − IL (no goal of its own; the CI is the evaluation's noise, not the training seed's)",
            ("libero_object.json",),
            when_run("rsft", episodes_paired("rsft", "il")),
        ),
        Row(
            "CSO − IL ≥ +10 points, CI above 0, ≥ 2 seeds",
            ("libero_object.json",),
            when_run("cso", gain(0.10, ci=True)),
        ),
    ],
}
LOG_ONLY = [
    ("Demo wall time (`./run.sh demo`)", "≤ 10 min on 2 cores", "log/demo.md"),
    ("Camera demo (`configs/metaworld_vision_demo.yaml`): gain and time", "shows the gain; ≤ 30 min", "log/camera.md"),
    ("MW-proxy wall time, three seeds from scratch", "≤ 90 min on 2 cores", "log/mw-proxy.md"),
    ("Policy rollouts on 2 cores ÷ scripted experts on 1", "≥ 1.6×", "log/rollout-efficiency.md"),
    ("Decode latency of one skill, batch 1", "≤ 10 ms p99", "log/control-loop.md"),
    ("30 Hz loop with a camera policy on the twin", "p99 ≤ 36.7 ms, no late tick", "log/control-loop.md"),
    ("Rollouts on 1 and 2 processes", "the ratio on 2 cores", "log/multi-process.md"),
    ("IL step rate: `lerobot-train` against in-memory frames", "— (serves the demo's time)", "log/il-step-rate.md"),
    ("R-SFT, SPO and evaluation on one GPU", "— (runs)", "log/gpu.md"),
]


# The README's plot: held-out IL, R-SFT and CSO per benchmark, (label, file, task on the twin or None)
PLOT = [
    ("MetaWorld state,\ndemo config (5 seeds)", "mw_proxy_demo.json", None),
    ("MetaWorld state,\nMW-proxy (5 seeds)", "mw_proxy.json", None),
    ("MetaWorld camera\n(4 seeds)", "mw_vision.json", None),
    ("PiPER twin, Press\nButton (100 trials)", "twin_table5_dm_press_t100.json", "press_button"),
    ("PiPER twin, Cube in\nBowl (100 trials)", "twin_table5_regrasp_cube.json", "cube_in_bowl"),
]


def plot(results_dir: Path, path: Path) -> None:
    """Held-out success of IL, R-SFT and CSO per benchmark: ± the std across training seeds on MetaWorld, one binomial
    standard error on the twin's trials."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 3.6))
    for i, method in enumerate(("il", "rsft", "cso")):
        means, errs = [], []
        for _, file, task in PLOT:
            r = json.loads((results_dir / file).read_text())
            if task is None:
                means.append(100 * r["methods"][method]["mean"])
                errs.append(100 * r["methods"][method]["std"])
            else:
                p, n = r["tasks"][task]["sr"][method], r["tasks"][task]["paired"]["cso_minus_il"]["trials"]
                means.append(100 * p)
                errs.append(100 * (p * (1 - p) / n) ** 0.5)
        x = [j + (i - 1) * 0.27 for j in range(len(PLOT))]
        ax.bar(x, means, 0.27, yerr=errs, capsize=3, label=name(method))
    ax.set_xticks(range(len(PLOT)), [label for label, _, _ in PLOT], fontsize=8)
    ax.set_ylabel("held-out success (%)")
    ax.set_ylim(0, 100)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(loc="upper right", fontsize=8, ncols=3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def anchor(file: str) -> str:
    return file.replace(".", "")


def render(results_dir: Path) -> str:
    """The page, from the results files in ``results_dir``."""
    used = {f for rows in SECTIONS.values() for row in rows for f in row.files}
    files: dict[str, Results] = {}
    for f in sorted(used):
        path = results_dir / f
        if not path.is_file():
            raise SystemExit(f"error: no results file {path}")
        files[f] = json.loads(path.read_text())
    link = "../benchmarks/results/"
    lines = [
        "# Results",
        "",
        "The current result of each benchmark goal, read from its committed results file by",
        "`benchmarks/results_page.py` (do not edit: rerun it after a results file changes;",
        "`tests/test_results_page.py` fails when this page and the files disagree). Success rates are % on held-out",
        "initial states. On MetaWorld, ± is the std across training seeds and [a, b] the 95 % t interval of the",
        "paired difference over seeds; on the twin, [a, b] is the 95 % interval over paired trials. Every run, with",
        f"its machine: [the log](log/README.md); every results file: [the index]({link}README.md).",
    ]
    for section, rows in SECTIONS.items():
        lines += [
            "",
            f"## {section}",
            "",
            "| goal | result (noise) | met? | date | file · command |",
            "|---|---|---|---|---|",
        ]
        for row in rows:
            result, met = row.read(*(files[f] for f in row.files))
            date = max(files[f]["date"] for f in row.files)
            # one file: it and its command; several: the files (their commands are on their own rows)
            one = len(row.files) == 1
            where = " · ".join(
                f"[`{f}`]({link}{f})" + (f" · [command](#{anchor(f)})" if one else "") for f in row.files
            )
            lines.append(f"| {row.goal} | {result} | {met} | {date} | {where} |")
    lines += [
        "",
        "## Measured, but in the log only",
        "",
        "These goals have no results file yet: their numbers stay in the log until a run writes one.",
        "",
        "| benchmark | goal | log |",
        "|---|---|---|",
    ]
    lines += [f"| {what} | {goal} | [{log}]({log}) |" for what, goal, log in LOG_ONLY]
    lines += ["", "## Commands", "", "Each file's `command`: the runs that wrote it, in order."]
    for f in sorted(used):
        lines += ["", f"### {f}", "", "```bash", *files[f]["command"].split("; "), "```"]
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--results_dir", type=Path, default=ROOT / "benchmarks" / "results")
    parser.add_argument("--page", type=Path, default=ROOT / "docs" / "results.md")
    parser.add_argument("--plot", type=Path, default=ROOT / "docs" / "img" / "results.png")
    parser.add_argument("--check", action="store_true", help="exit 1 when the page differs from what the files give")
    args = parser.parse_args()
    if not args.results_dir.is_dir():
        parser.error(f"no results folder {args.results_dir}")
    page = render(args.results_dir)
    if args.check:
        if not args.page.is_file() or args.page.read_text() != page:
            print(
                f"error: {args.page} differs from the results files; run python benchmarks/results_page.py",
                file=sys.stderr,
            )
            return 1
        return 0
    args.page.write_text(page)
    plot(args.results_dir, args.plot)
    print(f"[results_page] wrote {args.page} and {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
