"""``crosspath experiment loss-sweep``: passing time and safety against packet loss, in the lab.

Runs the ``rsu`` mode at each loss rate (a fraction 0..1, as every probability in
crosspath; default 0, 0.1, 0.3, 0.5, 0.8, 1) for
N trials in the network lab (``services.supervise.lab.runner.run_lab``: one
network namespace per daemon, ingress loss on every car's and RSU's air
interface), trial ``i`` with seed ``base_seed + i`` at every loss, one run after
another (daemon runs keep wall-clock time; parallel runs would compete for the
CPU). For reference the same trials also run in the in-process harness with the
same per-receiver loss (``ChannelModel(loss)``), and the stand-alone mode once
per seed (what 100 % loss should converge to).

Writes into the output directory:

``results.json``
    every lab run result (with its ``network`` and ``lab`` sections; no
    per-step trace), the in-process results, per-loss aggregates, failures;
``table.md``
    per loss: average passing time (lab, in-process), collisions, min PET, min
    gap, future-path delivery ratio, the loss measured by the nft rules, time
    spent coordinated and on-air rate per car;
``runs.csv``
    one row per run (lab, in-process, stand-alone reference): parameters and metrics;
``loss_sweep.png`` (and ``.pdf``, ``.svg``)
    average passing time, collisions and min PET against loss.

Decisions where the issue is silent: the min PET of a loss rate is the
smallest over its trials (the worst case, as safety is read), the passing time
the mean over trials of each run's mean over cars [95 % Student-t interval]. A failed
trial is reported (``errors``) and left out of the aggregates; the command
then exits 1 after writing what it has.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from services.edge.args import (
    add_scenario_option,
    float_at_least,
    fraction,
    non_negative_int,
    output_dir,
    positive_float,
    positive_int,
    run_speed,
)
from services.experiments.common import (
    Column,
    Stopwatch,
    Trial,
    TrialOutcome,
    collect_errors,
    fmt_ci,
    fmt_num,
    markdown_table,
    pyplot,
    run_in_process,
    run_trials,
    save_figure,
    summarize,
    trials_for,
    write_json,
    write_runs_csv,
)
from services.experiments.paper import DEFAULT_SCENARIO
from services.model.results import RunResult
from services.model.scenario import ScenarioError, load_scenario
from services.model.types import Policy, RunMode

__all__ = [
    "DEFAULT_LOSSES",
    "DEFAULT_OUT",
    "DEFAULT_TRIALS",
    "LabRunner",
    "aggregate",
    "configure",
    "loss_columns",
    "parse_losses",
    "render_table",
    "run",
    "run_sweep",
]

DEFAULT_LOSSES: Final = (0.0, 0.1, 0.3, 0.5, 0.8, 1.0)
"""Loss rates swept by default (fractions 0..1)."""
DEFAULT_TRIALS: Final = 3
DEFAULT_OUT: Final = Path("results") / "loss-sweep"
DEFAULT_SPEED: Final = 1.0


def parse_losses(text: str) -> tuple[float, ...]:
    """``"0,0.1,30%"`` → ``(0.0, 0.1, 0.3)``: fractions 0..1 (an explicit ``%`` converts);
    ``ValueError`` outside 0..1, for a bare number above 1, or repeated."""
    items = [v.strip() for v in text.split(",") if v.strip()]
    if not items:
        raise ValueError("no loss rate given")
    try:
        values = tuple(fraction(v) for v in items)
    except argparse.ArgumentTypeError as exc:
        raise ValueError(f"every loss rate {exc}") from None
    if len(set(values)) != len(values):
        raise ValueError(f"loss rates repeat: {text!r}")
    return values


def loss_columns(losses: Sequence[float], policy: Policy = Policy.PAPER) -> list[Column]:
    """One ``rsu``-mode column per loss rate (a probability, as ``Column.loss``)."""
    return [Column(f"loss{p:g}", f"loss {p:g}", RunMode.RSU, policy, loss=p) for p in losses]


@dataclass(frozen=True, slots=True)
class LabRunner:
    """Runs one trial in the network lab (a :class:`~services.experiments.common.Runner`).

    The column's loss (a probability) becomes the lab's ingress loss;
    ``burst`` and ``rate_mbit`` apply to every trial. Each trial's daemon logs go
    to ``run_dir_root/<column>-seed<N>``. Ctrl-C is not swallowed: the lab is
    torn down and the sweep stops.
    """

    speed: float = DEFAULT_SPEED
    run_dir_root: str | None = None
    burst: float | None = None
    rate_mbit: float | None = None
    timeout_s: float | None = None

    def __call__(self, trial: Trial) -> TrialOutcome:
        from services.supervise.lab.runner import run_lab

        t0 = time.perf_counter()
        run_dir = (
            None
            if self.run_dir_root is None
            else Path(self.run_dir_root) / f"{trial.column.key}-seed{trial.seed}"
        )
        try:
            result = run_lab(
                trial.scenario,
                trial.column.mode,
                trial.column.policy,
                trial.seed,
                trial.column.loss,
                burst=self.burst if trial.column.loss > 0 else None,
                rate_mbit=self.rate_mbit,
                speed=self.speed,
                run_dir=run_dir,
                timeout_s=self.timeout_s,
            )
        except Exception as exc:  # one failed trial is reported, not fatal to the sweep
            return TrialOutcome(
                trial, None, error=f"{type(exc).__name__}: {exc}", wall_s=time.perf_counter() - t0
            )
        wall = time.perf_counter() - t0
        if result.error is not None:
            return TrialOutcome(trial, None, error=result.error, wall_s=wall)
        return TrialOutcome(trial, result, None, None, wall)


# --------------------------------------------------------------------------- aggregates


def _lab_numbers(result: RunResult) -> dict[str, float | None]:
    """Per-run lab figures: fp delivery, measured loss, coordinated time, on-air rates."""
    fp = None if result.network is None else result.network.stream("fp")
    lab = result.lab or {}
    air: Mapping[str, Any] = lab.get("air") or {}
    radio = [n for n in lab.get("faults", {}).get("nodes", []) if n in air]
    seen = sum(int(air[n].get("loss_seen", 0)) for n in radio)
    dropped = sum(int(air[n].get("loss_dropped", 0)) for n in radio)
    cars = [c for c in result.vehicles if c in air]
    modes: Mapping[str, Any] = lab.get("modes") or {}

    def mean(values: list[float]) -> float | None:
        return sum(values) / len(values) if values else None

    return {
        "fp_delivery": None if fp is None else fp.delivery_ratio,
        "measured_loss": dropped / seen if seen else None,
        "coordinated_s": mean(
            [float(modes[c]["coordinated_s"]) for c in result.vehicles if c in modes]
        ),
        "air_tx_kbps": mean([float(air[c]["tx_kbps"]) for c in cars if air[c].get("tx_kbps")]),
        "v2x_tx_kbps": mean(
            [float(air[c]["daemon_tx_kbps"]) for c in cars if air[c].get("daemon_tx_kbps")]
        ),
    }


def aggregate(results: Sequence[RunResult], lab: bool) -> dict[str, Any]:
    """Aggregates of one loss rate's runs (see the module docstring)."""
    pets = [r.min_pet_s for r in results]
    gaps = [r.min_gap_m for r in results]
    out: dict[str, Any] = {
        "runs": len(results),
        "average_passing_time_s": summarize([r.mean_passing_time_s for r in results]),
        "collisions": sum(r.collisions for r in results),
        "runs_with_collision": sum(1 for r in results if r.collisions > 0),
        "all_finished": sum(1 for r in results if r.all_finished),
        "min_pet_s": min((p for p in pets if p is not None), default=None),
        "mean_min_pet_s": summarize(pets)["mean"],
        "min_gap_m": min((g for g in gaps if g is not None), default=None),
    }
    if lab:
        numbers = [_lab_numbers(r) for r in results]
        for key in (
            "fp_delivery",
            "measured_loss",
            "coordinated_s",
            "air_tx_kbps",
            "v2x_tx_kbps",
        ):
            out[key] = summarize([n[key] for n in numbers])["mean"]
    return out


def render_table(doc: Mapping[str, Any]) -> str:
    """The sweep as a markdown table, one row per loss rate."""
    header = [
        "loss",
        "avg passing (lab) [s]",
        "avg passing (in-process) [s]",
        "collisions",
        "min PET [s]",
        "min gap [m]",
        "fp delivery",
        "measured loss",
        "coordinated [s/car]",
        "air tx [kbps/car]",
        "V2X payload [kbps/car]",
    ]
    rows: list[list[str]] = []
    for col in doc["columns"]:
        key = col["key"]
        a = doc["aggregates"]["lab"].get(key, {})
        s = doc["aggregates"]["in_process"].get(key, {})
        pt = a.get("average_passing_time_s", {})
        spt = s.get("average_passing_time_s", {})
        rows.append(
            [
                col["title"],
                fmt_ci(pt) if pt else "–",
                fmt_num(spt.get("mean")),
                f"{a.get('collisions', '–')} in {a.get('runs_with_collision', 0)}"
                f" / {a.get('runs', 0)} runs",
                fmt_num(a.get("min_pet_s")),
                fmt_num(a.get("min_gap_m")),
                fmt_num(a.get("fp_delivery"), digits=3),
                fmt_num(a.get("measured_loss"), digits=3),
                fmt_num(a.get("coordinated_s"), digits=1),
                fmt_num(a.get("air_tx_kbps"), digits=1),
                fmt_num(a.get("v2x_tx_kbps"), digits=1),
            ]
        )
    ref = doc.get("standalone_reference", {}).get("average_passing_time_s", {}).get("mean")
    table = markdown_table(header, rows)
    notes = [
        f"`rsu` mode, policy {doc['policy']}, {doc['trials']} trial(s) per loss (seeds "
        f"{doc['base_seed']}..{doc['base_seed'] + doc['trials'] - 1}), lab at speed "
        f"{doc['speed']:g}; ingress loss on every car and RSU (per receiver).",
        f"Stand-alone (no V2X, in-process, same seeds): average passing {fmt_num(ref)} s.",
        "avg passing (lab): mean over runs [95 % Student-t interval]; collisions: total in"
        " k / N runs with one.",
        "min PET: smallest over the trials; measured loss: packets dropped by the nft rules "
        "over packets they saw; air tx: interface bytes (all headers, one copy per "
        "receiver) per run second; V2X payload: the daemons' own count.",
    ]
    return table + "\n\n" + "\n".join(f"- {n}" for n in notes) + "\n"


def plot_sweep(doc: Mapping[str, Any], path: Path) -> list[str]:
    """Average passing time (mean, 95 % t-interval), collisions and min PET against
    loss, lab and in-process; PNG at 300 dpi, PDF and SVG. Returns the files written."""
    plt = pyplot()
    cols = doc["columns"]
    x = [100.0 * float(c["loss"]) for c in cols]
    fig, axes = plt.subplots(1, 3, figsize=(7.16, 2.8))

    def series(harness: str, key: str, field: str | None = None) -> list[float]:
        out: list[float] = []
        for c in cols:
            a = doc["aggregates"][harness].get(c["key"], {})
            v = a.get(key)
            if field is not None and isinstance(v, Mapping):
                v = v.get(field)
            out.append(float("nan") if v is None else float(v))
        return out

    ax = axes[0]
    mean = series("lab", "average_passing_time_s", "mean")
    low = series("lab", "average_passing_time_s", "ci95_low")
    high = series("lab", "average_passing_time_s", "ci95_high")
    yerr = [
        [0.0 if math.isnan(lo) else m - lo for m, lo in zip(mean, low, strict=True)],
        [0.0 if math.isnan(hi) else hi - m for m, hi in zip(mean, high, strict=True)],
    ]
    ax.errorbar(x, mean, yerr=yerr, marker="o", capsize=3, label="lab, 95 % CI")
    ax.plot(
        x,
        series("in_process", "average_passing_time_s", "mean"),
        "s--",
        alpha=0.7,
        label="in-process",
    )
    ref = doc.get("standalone_reference", {}).get("average_passing_time_s", {}).get("mean")
    if ref is not None:
        ax.axhline(ref, color="grey", ls=":", label="stand-alone")
    ax.set_ylabel("average passing time [s]", fontsize=8)
    ax.legend(fontsize=6)
    ax = axes[1]
    width = 3.0
    ax.bar([v - width / 2 for v in x], series("lab", "collisions"), width, label="lab")
    ax.bar(
        [v + width / 2 for v in x],
        series("in_process", "collisions"),
        width,
        label="in-process",
        alpha=0.7,
    )
    for v, c in zip(x, series("lab", "collisions"), strict=True):
        if c == c:  # not NaN
            ax.annotate(f"{c:g}", (v - width / 2, c), ha="center", va="bottom", fontsize=8)
    ax.set_ylabel(f"collisions (sum over {doc['trials']} trials)", fontsize=8)
    ax.set_ylim(bottom=0, top=max(1.0, *[v for v in series("lab", "collisions") if v == v]))
    ax.legend(fontsize=6)
    ax = axes[2]
    ax.plot(x, series("lab", "min_pet_s"), "o-", label="lab (min over trials)")
    ax.plot(x, series("in_process", "min_pet_s"), "s--", alpha=0.7, label="in-process")
    ax.set_ylabel("min PET [s]", fontsize=8)
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=6)
    for ax in axes:
        ax.set_xlabel("air packet loss [%]", fontsize=8)
        ax.grid(True, lw=0.3, alpha=0.5)
        ax.tick_params(labelsize=7)
    fig.suptitle(f"{doc['scenario_name']}: rsu mode against packet loss", fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)


def runs_rows(doc: Mapping[str, Any]) -> list[dict[str, Any]]:
    """``runs.csv``'s rows: one per run (lab, in-process and the stand-alone reference)."""
    rows: list[dict[str, Any]] = []
    loss_of = {c["key"]: c["loss"] for c in doc["columns"]}
    groups: list[tuple[str, str, str, list[Any]]] = []
    for harness in ("lab", "in_process"):
        for key, runs in doc["runs"][harness].items():
            groups.append((harness, key, str(RunMode.RSU), runs))
    groups.append(
        ("in_process", "standalone", str(RunMode.STANDALONE), doc["runs"]["standalone_in_process"])
    )
    for harness, key, mode, runs in groups:
        for trial, raw in enumerate(runs):
            r = RunResult.model_validate(raw)
            rows.append(
                {
                    "experiment": "loss-sweep",
                    "scenario": doc["scenario_name"],
                    "harness": harness,
                    "column": key,
                    "mode": mode,
                    "policy": doc["policy"] if mode == str(RunMode.RSU) else "",
                    "loss": loss_of.get(key, 0.0),
                    "speed": doc["speed"] if harness == "lab" else "",
                    "trial": trial,
                    "seed": r.seed,
                    "collisions": r.collisions,
                    "min_gap_m": r.min_gap_m,
                    "min_pet_s": r.min_pet_s,
                    "all_finished": r.all_finished,
                    "mean_passing_time_s": r.mean_passing_time_s,
                    "sim_s": r.sim_s,
                }
            )
    return rows


# --------------------------------------------------------------------------- the sweep


def run_sweep(
    scenario_path: str | Path = DEFAULT_SCENARIO,
    losses: Sequence[float] = DEFAULT_LOSSES,
    trials: int = DEFAULT_TRIALS,
    seed: int = 0,
    out_dir: str | Path = DEFAULT_OUT,
    *,
    speed: float = DEFAULT_SPEED,
    policy: Policy = Policy.PAPER,
    burst: float | None = None,
    rate_mbit: float | None = None,
    timeout_s: float | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Run the sweep and write ``results.json``, ``runs.csv``, ``table.md`` and
    ``loss_sweep.png`` (with ``.pdf`` and ``.svg``).

    Returns the document written as ``results.json`` (its ``errors`` lists failed
    trials). Raises ``ValueError`` for bad arguments, ``ScenarioError`` for an
    unusable scenario, ``LabInterrupted`` on Ctrl-C (nothing is written then).
    """
    watch = Stopwatch()
    t0 = time.perf_counter()
    scenario_file = Path(scenario_path)
    scenario = load_scenario(scenario_file)
    if not (0.0 < speed <= 1000.0):
        raise ValueError(f"speed must be in (0, 1000], got {speed}")
    columns = loss_columns(losses, policy)
    out = Path(out_dir)
    plan = trials_for(columns, scenario_file, trials, seed, trace=False)
    runner = LabRunner(speed, str(out / "runs"), burst, rate_mbit, timeout_s)
    with watch.phase("lab_s"):
        lab_outcomes = run_trials(
            plan, runner, jobs=1, progress=progress, description="loss sweep (lab)"
        )
    with watch.phase("in_process_s"):
        sim_outcomes = run_trials(plan, run_in_process, progress=False)
        standalone = [Column("standalone", "Stand-alone", RunMode.STANDALONE)]
        ref_outcomes = run_trials(
            trials_for(standalone, scenario_file, trials, seed, trace=False),
            run_in_process,
            progress=False,
        )
    errors = collect_errors(lab_outcomes) + collect_errors(sim_outcomes + ref_outcomes)

    def by_column(outcomes: Sequence[TrialOutcome]) -> dict[str, list[RunResult]]:
        runs: dict[str, list[RunResult]] = {c.key: [] for c in columns}
        for o in outcomes:
            if o.result is not None:
                runs.setdefault(o.trial.column.key, []).append(o.result)
        return runs

    lab_runs = by_column(lab_outcomes)
    sim_runs = by_column(sim_outcomes)
    ref_results = [o.result for o in ref_outcomes if o.result is not None]
    doc: dict[str, Any] = {
        "experiment": "loss-sweep",
        "scenario": str(scenario_file),
        "scenario_name": scenario.name,
        "harness": "lab",
        "mode": str(RunMode.RSU),
        "policy": str(policy),
        "trials": trials,
        "base_seed": seed,
        "speed": speed,
        "losses": list(losses),
        "burst": burst,
        "rate_mbit": rate_mbit,
        "columns": [{"key": c.key, "title": c.title, "loss": c.loss} for c in columns],
        "aggregates": {
            "lab": {k: aggregate(v, lab=True) for k, v in lab_runs.items()},
            "in_process": {k: aggregate(v, lab=False) for k, v in sim_runs.items()},
        },
        "standalone_reference": aggregate(ref_results, lab=False),
        "errors": errors,
        "runs": {
            "lab": {k: [r.to_dict() for r in v] for k, v in lab_runs.items()},
            "in_process": {k: [r.to_dict() for r in v] for k, v in sim_runs.items()},
            "standalone_in_process": [r.to_dict() for r in ref_results],
        },
    }
    out.mkdir(parents=True, exist_ok=True)
    with watch.phase("figures_s"):
        plot_sweep(doc, out / "loss_sweep.png")
    write_runs_csv(out / "runs.csv", runs_rows(doc))
    doc["timing"] = {
        "wall_s": round(time.perf_counter() - t0, 3),
        "sum_of_lab_run_wall_s": round(sum(o.wall_s for o in lab_outcomes), 3),
        **watch.phases,
    }
    (out / "table.md").write_text(render_table(doc))
    write_json(out / "results.json", doc)
    return doc


# --------------------------------------------------------------------------- CLI


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath experiment loss-sweep``; bad values are refused while parsing."""

    def loss_list(text: str) -> tuple[float, ...]:
        try:
            return parse_losses(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    parser.add_argument("--out", type=output_dir, default=DEFAULT_OUT, help="output directory")
    parser.add_argument(
        "--trials", type=positive_int, default=DEFAULT_TRIALS, help="trials per loss rate"
    )
    parser.add_argument(
        "--losses",
        type=loss_list,
        default=",".join(f"{v:g}" for v in DEFAULT_LOSSES),
        help="loss rates, fractions 0..1 (or 30%%), comma-separated",
    )
    parser.add_argument(
        "--speed",
        type=run_speed,
        default=DEFAULT_SPEED,
        help="run seconds per wall second of the lab runs (2-4 for a quick look)",
    )
    parser.add_argument(
        "--seed", type=non_negative_int, default=0, help="base seed: trial i uses seed + i"
    )
    parser.add_argument(
        "--policy",
        choices=[p.value for p in Policy],
        default=Policy.PAPER.value,
        help="the RSU's velocity manager",
    )
    add_scenario_option(parser)
    parser.add_argument(
        "--burst",
        type=float_at_least(1.0),
        default=None,
        help="mean loss burst in packets (Gilbert model); default: independent losses",
    )
    parser.add_argument(
        "--rate",
        type=positive_float,
        default=None,
        help="air rate limit of every car and RSU [Mbit/s]",
    )
    parser.add_argument(
        "--timeout",
        type=positive_float,
        default=None,
        help="wall s per run (default max_sim / speed + 60)",
    )


def run(args: argparse.Namespace) -> int:
    """The sweep; 0 when every trial ran, 1 when some failed, 2 on bad arguments."""
    from services.supervise.lab.faults import Loss
    from services.supervise.lab.netns import prerequisites
    from services.supervise.lab.runner import LabInterrupted

    name = "crosspath experiment loss-sweep"
    losses: tuple[float, ...] = args.losses
    try:  # an impossible loss model fails here, not in every trial
        for loss in losses:
            if loss > 0.0:
                Loss(loss, args.burst)
    except ValueError as exc:
        print(f"{name}: --burst: {exc}", file=sys.stderr)
        return 2
    missing = prerequisites()
    if missing:
        print(f"{name}: the lab needs {', '.join(missing)} (run as root)", file=sys.stderr)
        return 2
    try:
        doc = run_sweep(
            args.scenario,
            losses,
            args.trials,
            args.seed,
            args.out,
            speed=args.speed,
            policy=Policy(args.policy),
            burst=args.burst,
            rate_mbit=args.rate,
            timeout_s=args.timeout,
        )
    except (ScenarioError, ValueError) as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 2
    except LabInterrupted as exc:
        print(f"{name}: interrupted ({exc}); nothing written", file=sys.stderr)
        return 128 + exc.signum
    print(render_table(doc))
    print(
        f"{len(losses)} loss rates x {args.trials} trial(s) in {doc['timing']['wall_s']:.0f} s;"
        f" wrote results.json, table.md and loss_sweep.png to {args.out}"
    )
    if doc["errors"]:
        print(
            f"{name}: {len(doc['errors'])} trial(s) failed:\n  " + "\n  ".join(doc["errors"]),
            file=sys.stderr,
        )
        return 1
    return 0
