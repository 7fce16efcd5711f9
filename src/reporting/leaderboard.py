"""Leaderboard: every method at its own best training budget, the budget chosen on validation views only.

``python -m src.tables SWEEP_DIR... --leaderboard [--reference EXPERIMENT] --out OUT``.

A *method* is the record's ``experiment`` (else ``method``) plus `` + <sparse>`` when ``choices.sparse``
is set and not ``none``. Its candidate budgets are the values of ``keys.budget_scale`` (else
``keys.iterations``) among its runs. For every method and view count (``keys.n_views``) the budget
is chosen on the final validation PSNR, the last point of the run's ``curve`` when ``curve_split`` is
``val``: its *score* is the mean over scenes (of the mean over seeds). Budgets are tried from the cheapest up,
and a larger one replaces the current choice only when it scores higher on the (scene, seed) pairs the two
share, so a budget run on one seed is compared with the choice on that seed alone, and the cheaper budgets
keep their comparison on all the seeds they share; equal scores keep the cheaper budget. A run without a
validation curve cannot be selected. Test views are read only for the reported numbers at the chosen budget:

* test PSNR / SSIM: mean over scenes, ± the std over seeds of the scene mean (seeds covering every
  scene, at least two);
* total training time: ``train_s`` + ``stage1_train_s`` (two-stage methods) + ``capacity_search_s``,
  mean over scenes;
* validation PSNR *at equal wall time*: each run's validation curve (its clock shifted by the first
  stage and capacity search) linearly interpolated at the reference method's mean total training
  time, per scene, then averaged; past the end of a curve its last value, flagged "†"; before its
  first point "–". A longer schedule read part-way can sit in an opacity-reset dip, so beside it:
* test PSNR *within the reference's time*: the method at the best of its budgets whose total training time is at
  most the reference's (chosen on validation views by the same rule), i.e. what that much time buys when the
  schedule is made for it; "–" when no budget tried fits.

Outputs (:func:`write_leaderboard`): ``leaderboard.md``, ``leaderboard.json`` and
``leaderboard_curves.{png,svg}`` (validation PSNR against total wall time at the chosen budgets,
with the Pareto front over all methods' points); beside them the CLI keeps ``runs.jsonl.gz``, every run read
(:mod:`src.reporting.archive`), from which the board is rebuilt or extended.
"""

from __future__ import annotations

import itertools
import json
import math
import statistics
import sys
from collections import defaultdict
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TypeVar

from src.reporting.aggregate import dedupe, sort_key
from src.reporting.archive import write_archive
from src.reporting.chart import Point, pareto_front, read_curve
from src.reporting.collect import Collection, RunRecord
from src.utils.record import OutputBusy, atomic_write_text, cli_error, os_error_line, output_lock

DEFAULT_REFERENCE = "splatfields3d_mip"
DASH = "–"
PAST_END = "†"
LARGEST = "↑"  # the chosen budget is the largest one scored: a larger budget was not tried
VAL_SPLIT = "val"
BUDGET_KEYS = ("budget_scale", "iterations")
TIE_TOLERANCE = 1e-9  # selection scores closer than this (dB) are equal
SELECTION_RULE = (
    "For every method and view count a budget (keys.budget_scale, else keys.iterations) is chosen on the mean "
    "final validation PSNR over scenes and seeds: from the cheapest up, a larger budget replaces the choice only "
    "when it scores higher on the scenes and seeds the two share (ties keep the cheaper one; the val column is "
    "each budget's mean over its own runs); test views are read only for the numbers reported at that budget."
)


# -- runs -----------------------------------------------------------------------------------------


@dataclass(frozen=True, order=True)
class Budget:
    """A candidate training budget; a smaller ``value`` is cheaper. ``key`` is "" when a run has none."""

    value: float
    key: str = ""

    def label(self) -> str:
        """``×2`` for a budget scale, ``3000 it`` for an iteration count, "?" when unknown."""
        if self.key == "budget_scale":
            return f"×{self.value:g}"
        return f"{self.value:g} it" if self.key == "iterations" else "?"

    def name(self) -> str:
        """``budget_scale=2``: the budget's key in ``leaderboard.json``."""
        return f"{self.key or 'budget'}={self.value:g}"


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


def method_label(record: RunRecord) -> str:
    """``experiment`` (else ``method``), plus `` + <sparse>`` when ``choices.sparse`` is set and not ``none``,
    plus `` (first stage + <sparse>)`` when a two-stage run's first stage has its own (``stage1.sparse``)."""
    choices = record.data.get("choices") or {}
    name = str(record.data.get("experiment") or record.data.get("method") or "?")
    sparse, first = choices.get("sparse"), choices.get("sparse@stage1.sparse")
    label = f"{name} + {sparse}" if sparse not in (None, "", "none") else name
    return f"{label} (first stage + {first})" if first not in (None, "", "none") else label


def budget_of(record: RunRecord) -> Budget:
    """The run's budget: ``keys.budget_scale``, else ``keys.iterations``, else an unknown one."""
    keys = record.data.get("keys") or {}
    for name in BUDGET_KEYS:
        value = _number(keys.get(name))
        if value is not None:
            return Budget(value, name)
    return Budget(math.inf)


@dataclass(frozen=True)
class Run:
    """One record as the leaderboard sees it: method, view count, budget, scene and seed."""

    record: RunRecord
    method: str
    n_views: Any
    budget: Budget
    scene: str
    seed: Any

    @classmethod
    def of(cls, record: RunRecord) -> Run:
        """The leaderboard's view of ``record``."""
        keys = record.data.get("keys") or {}
        return cls(record, method_label(record), keys.get("n_views"), budget_of(record),
                   str(keys.get("scene", "")), keys.get("seed"))  # fmt: skip

    @property
    def ok(self) -> bool:
        return self.record.status == "ok"

    def offset(self) -> float:
        """Seconds of training before the curve's clock started: a first stage and a capacity search."""
        return (self.record.metric("stage1_train_s") or 0.0) + (self.record.metric("capacity_search_s") or 0.0)

    def total_time(self) -> float | None:
        """``train_s`` plus :meth:`offset`; None without ``train_s``."""
        t = self.record.metric("train_s")
        return None if t is None else t + self.offset()

    def val_curve(self) -> list[tuple[float, float]]:
        """(total wall time, validation PSNR) points in time order; [] without a validation curve."""
        if self.record.data.get("curve_split") != VAL_SPLIT:
            return []
        shift = self.offset()
        return [(t + shift, y) for t, y in read_curve(self.record)]

    def final_val(self) -> float | None:
        """Validation PSNR at the end of training (the last curve point), or None."""
        curve = self.val_curve()
        return curve[-1][1] if curve else None

    def test(self, metric: str) -> float | None:
        """A test metric of the run (``psnr``, ``ssim``)."""
        return self.record.metric(metric)


def read_runs(records: Iterable[RunRecord]) -> list[Run]:
    """One :class:`Run` per distinct run (duplicates across sweep directories count once)."""
    kept, _ = dedupe(records)
    return [Run.of(r) for r in sorted(kept, key=lambda r: r.path)]


# -- statistics -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Stat:
    """Mean over scenes; std over seeds of the scene mean (None under two seeds covering every scene)."""

    mean: float | None
    std: float | None = None
    n_seeds: int = 0


Value = Callable[[Run], float | None]
K = TypeVar("K")  # a grouping key of runs (a scene, or a (scene, seed) pair)


def _values(runs: Iterable[Run], value: Value) -> list[tuple[Run, float]]:
    pairs = [(run, value(run)) for run in runs if run.ok]
    return [(run, v) for run, v in pairs if v is not None]


def means_by(runs: Iterable[Run], value: Value, key: Callable[[Run], K]) -> dict[K, float]:
    """``key(run)`` → mean of ``value`` over the ok runs that have one (e.g. per scene, or per (scene, seed))."""
    groups: dict[K, list[float]] = defaultdict(list)
    for run, v in _values(runs, value):
        groups[key(run)].append(v)
    return {k: statistics.fmean(vs) for k, vs in groups.items()}


def scene_means(runs: Iterable[Run], value: Value) -> dict[str, float]:
    """Scene → mean over seeds of ``value`` over the ok runs that have one."""
    return means_by(runs, value, lambda run: run.scene)


def stat_of(runs: Sequence[Run], value: Value) -> Stat:
    """Mean over scenes of the seed means, and the spread over seeds of each seed's scene mean."""
    scenes = scene_means(runs, value)
    by_seed: dict[str, dict[str, float]] = defaultdict(dict)  # seed -> scene -> mean of that seed's runs
    for (seed, scene), v in means_by(runs, value, lambda run: (str(run.seed), run.scene)).items():
        by_seed[seed][scene] = v
    complete = [d for d in by_seed.values() if set(d) == set(scenes)]
    means = [statistics.fmean(d.values()) for d in complete]
    std = statistics.stdev(means) if len(means) >= 2 else None
    return Stat(statistics.fmean(scenes.values()) if scenes else None, std, len(by_seed))


def interpolate(curve: Sequence[tuple[float, float]], t: float) -> tuple[float | None, bool]:
    """The curve's value at time ``t`` (linear between points) and whether ``t`` is past its end.

    Past the last point: (last value, True). Before the first point or on an empty curve: (None, False).
    """
    if not curve or t < curve[0][0]:
        return None, False
    if t >= curve[-1][0]:
        return curve[-1][1], t > curve[-1][0]
    for (t0, y0), (t1, y1) in itertools.pairwise(curve):
        if t0 <= t <= t1:
            return (y0 if t1 == t0 else y0 + (y1 - y0) * (t - t0) / (t1 - t0)), False
    return curve[-1][1], False


@dataclass(frozen=True)
class AtTime:
    """Validation PSNR at ``time_s``: None when a curve starts later; ``past_end`` when a run had already ended."""

    time_s: float
    value: float | None
    past_end: bool = False


def equal_time(runs: Iterable[Run], t: float) -> AtTime:
    """Mean over scenes (of seeds) of the ok runs' validation curves at total wall time ``t``.

    ``past_end`` when ``t`` is later than some run's end (its total training time, else its last point).
    """
    per_scene: dict[str, list[float | None]] = defaultdict(list)
    past = False
    for run in runs:
        curve = run.val_curve() if run.ok else []
        if curve:
            value, _ = interpolate(curve, t)
            per_scene[run.scene].append(value)
            past |= value is not None and t > max(curve[-1][0], run.total_time() or 0.0)
    if not per_scene or any(v is None for vs in per_scene.values() for v in vs):
        return AtTime(t, None)
    scenes = [statistics.fmean(v for v in vs if v is not None) for vs in per_scene.values()]
    return AtTime(t, statistics.fmean(scenes), past)


def budget_time(runs: Iterable[Run]) -> float | None:
    """Total training time of one budget's runs: mean over scenes (of seeds); None without a timed run."""
    times = scene_means(runs, Run.total_time)
    return statistics.fmean(times.values()) if times else None


def mean_curve(curves: Sequence[Sequence[tuple[float, float]]]) -> list[tuple[float, float]]:
    """Point-by-point mean (by index) of several curves, up to the shortest one's length."""
    curves = [c for c in curves if c]
    if not curves:
        return []
    n = min(len(c) for c in curves)
    return [(statistics.fmean(c[i][0] for c in curves), statistics.fmean(c[i][1] for c in curves)) for i in range(n)]


def pareto_staircase(points: Iterable[tuple[float, float]]) -> list[tuple[float, float]]:
    """The (time, PSNR) points no other point beats (as fast or faster and at least as good), by time."""
    front = pareto_front([Point("", "", x, 0.0, y, 0.0, 1) for x, y in points])
    return [(p.x, p.y) for p in front]


# -- budget selection -----------------------------------------------------------------------------


@dataclass(frozen=True)
class BudgetScore:
    """A candidate budget: its score over its own runs, each (scene, seed)'s final validation PSNR, its runs."""

    budget: Budget
    score: float | None
    scenes: tuple[str, ...]
    n_runs: int
    n_failed: int
    n_unfinished: int
    n_no_val: int  # ok runs without a validation curve
    finals: dict[tuple[str, str], float] = field(default_factory=dict)  # (scene, seed) -> final val PSNR

    @property
    def seeds(self) -> set[str]:
        return {seed for _, seed in self.finals}


def mean_of_scenes(finals: Mapping[tuple[str, str], float], pairs: Iterable[tuple[str, str]]) -> float | None:
    """Mean over scenes of the mean over seeds of ``finals`` on ``pairs``; None without a pair."""
    by_scene: dict[str, list[float]] = defaultdict(list)
    for scene, seed in pairs:
        by_scene[scene].append(finals[(scene, seed)])
    return statistics.fmean(statistics.fmean(vs) for vs in by_scene.values()) if by_scene else None


def score_budgets(groups: Mapping[Budget, Sequence[Run]]) -> dict[Budget, BudgetScore]:
    """Each budget's mean final validation PSNR over its own (scene, seed) pairs, and the pairs' values."""
    scores = {}
    for budget in sorted(groups):
        runs = groups[budget]
        finals = means_by(runs, Run.final_val, lambda run: (run.scene, str(run.seed)))
        scores[budget] = BudgetScore(
            budget, mean_of_scenes(finals, finals), tuple(sorted({scene for scene, _ in finals})), len(runs),
            sum(r.record.status == "failed" for r in runs),
            sum(r.record.status in ("running", "interrupted") for r in runs),
            sum(r.ok and not r.val_curve() for r in runs), finals,
        )  # fmt: skip
    return scores


def _pairs_text(pairs: Iterable[tuple[str, str]]) -> str:
    scenes, seeds = sorted({sc for sc, _ in pairs}), sorted({sd for _, sd in pairs})
    return f"{', '.join(scenes)}; seed {', '.join(seeds)}"


def choose_budget(scores: Mapping[Budget, BudgetScore]) -> tuple[Budget | None, list[str]]:
    """The chosen budget and how it was compared; None when no budget has a score.

    From the cheapest budget up, a larger one replaces the current choice only when its score on the (scene,
    seed) pairs the two share is higher; without a shared pair the two are compared on their own runs.
    """
    chosen: Budget | None = None
    notes = []
    for budget, s in sorted(scores.items()):
        if s.score is None:
            continue
        if chosen is None:
            chosen = budget
            continue
        held = scores[chosen].finals
        shared = sorted(held.keys() & s.finals.keys())
        if shared:
            new, old = mean_of_scenes(s.finals, shared), mean_of_scenes(held, shared)
            if set(shared) != set(held) or set(shared) != set(s.finals):
                notes.append(f"{budget.label()} against {chosen.label()} on the runs both have "
                             f"({_pairs_text(shared)}): {new:.2f} vs {old:.2f}")  # fmt: skip
        else:
            new, old = s.score, scores[chosen].score
            notes.append(f"{budget.label()} and {chosen.label()} share no (scene, seed) pair: compared on their "
                         "own runs")  # fmt: skip
        assert new is not None and old is not None
        if new > old + TIE_TOLERANCE:
            chosen = budget
    return chosen, notes


def _budget_notes(scores: Mapping[Budget, BudgetScore], chosen: Budget | None) -> list[str]:
    """Why a budget could not be selected, and choices that unfinished runs may still change."""
    notes = []
    for b, s in scores.items():
        if s.n_no_val:
            notes.append(f"{b.label()}: {s.n_no_val} ok run(s) without a validation curve (curve_split "
                         f"'{VAL_SPLIT}') cannot be selected")  # fmt: skip
        if s.score is None and not s.n_no_val:
            notes.append(f"{b.label()}: no ok run with a validation curve, cannot be selected")
        if s.n_unfinished and chosen is not None and len(scores) > 1:
            notes.append(f"{b.label()}: {s.n_unfinished} unfinished run(s); the choice may change")
    return notes


@dataclass(frozen=True)
class WithinTime:
    """A method at the best of its budgets that fit in ``time_s``: among the budgets whose total training time
    (:func:`budget_time`) is at most ``time_s``, the one :func:`choose_budget` picks on validation views, with
    its validation score, test PSNR and time. What a user with that much time would train."""

    time_s: float
    budget: Budget
    val_psnr: float | None
    test_psnr: Stat
    train_s: float | None


# -- the leaderboard ------------------------------------------------------------------------------


@dataclass
class Entry:
    """One leaderboard row: a method at one view count, at its chosen budget."""

    method: str
    n_views: Any
    scores: dict[Budget, BudgetScore]
    chosen: Budget | None
    runs: list[Run]  # every run of the method at this view count
    notes: list[str] = field(default_factory=list)
    at_ref: AtTime | None = None
    within_ref: WithinTime | None = None

    @property
    def chosen_runs(self) -> list[Run]:
        return self.budget_runs(self.chosen) if self.chosen is not None else []

    def stat(self, metric: str) -> Stat:
        """Test ``metric`` at the chosen budget (empty without a chosen budget)."""
        return stat_of(self.chosen_runs, lambda r: r.test(metric)) if self.chosen else Stat(None)

    def train_s(self) -> float | None:
        """Total training time at the chosen budget, mean over scenes (of seeds)."""
        return budget_time(self.chosen_runs)

    def budget_runs(self, budget: Budget) -> list[Run]:
        return [r for r in self.runs if r.budget == budget]

    def val_score(self) -> float | None:
        return self.scores[self.chosen].score if self.chosen else None

    def chose_largest(self) -> bool:
        """Whether the chosen budget is the largest with a validation score: no larger budget was tried, so the
        method may not have converged (its row may sit below its best)."""
        scored = [b for b, s in self.scores.items() if s.score is not None]
        return self.chosen is not None and self.chosen == max(scored)

    def budget_label(self) -> str:
        """The chosen budget's label (``×2``), marked ``↑`` when it is the largest tried; "" without one."""
        return self.chosen.label() + (LARGEST if self.chose_largest() else "") if self.chosen else ""

    def iterations(self) -> list[Any]:
        """The distinct ``keys.iterations`` of the chosen budget's runs."""
        values = {(r.record.data.get("keys") or {}).get("iterations") for r in self.chosen_runs}
        return sorted((v for v in values if v is not None), key=sort_key)

    def curve(self) -> list[tuple[float, float]]:
        """Mean validation curve (by index) of the chosen budget's ok runs, on total wall time."""
        return mean_curve([r.val_curve() for r in self.chosen_runs if r.ok])


@dataclass
class Leaderboard:
    """Entries sorted per view count by test PSNR, the reference and its training times, footnotes, notes."""

    entries: list[Entry]
    reference: str
    ref_times: dict[Any, float | None]
    footnotes: list[Run]  # runs that did not finish ok, numbered from 1
    notes: list[str] = field(default_factory=list)

    def views(self) -> list[Any]:
        return sorted({e.n_views for e in self.entries}, key=sort_key)

    def scenes(self, n_views: Any) -> list[str]:
        return sorted({r.scene for e in self.entries if e.n_views == n_views for r in e.runs})

    def footnote(self, run: Run) -> int:
        return next(i for i, r in enumerate(self.footnotes, 1) if r is run)


def make_entry(method: str, n_views: Any, runs: list[Run]) -> Entry:
    """Score the method's budgets at one view count and choose one."""
    groups: dict[Budget, list[Run]] = defaultdict(list)
    for run in runs:
        groups[run.budget].append(run)
    scores = score_budgets(groups)
    chosen, notes = choose_budget(scores)
    return Entry(method, n_views, scores, chosen, runs, notes + _budget_notes(scores, chosen))


def within_time(entry: Entry, t: float) -> WithinTime | None:
    """``entry``'s method at the best of its budgets that fit in ``t`` seconds; None when none fits."""
    fitting = {b: s for b, s in entry.scores.items()
               if (bt := budget_time(entry.budget_runs(b))) is not None and bt <= t}  # fmt: skip
    chosen, _ = choose_budget(fitting)
    if chosen is None:
        return None
    runs = entry.budget_runs(chosen)
    return WithinTime(t, chosen, fitting[chosen].score, stat_of(runs, _test_psnr), budget_time(runs))


def _order(entry: Entry) -> tuple:
    psnr = entry.stat("psnr").mean
    return (sort_key(entry.n_views), psnr is None, -(psnr or 0.0), entry.method)


def build_leaderboard(records: Iterable[RunRecord], reference: str = DEFAULT_REFERENCE) -> Leaderboard:
    """The leaderboard of ``records``; the equal-time column uses ``reference``'s mean training time."""
    groups: dict[tuple[str, Any], list[Run]] = defaultdict(list)
    for run in read_runs(records):
        groups[(run.method, json.dumps(run.n_views, default=str))].append(run)
    entries = sorted((make_entry(m, runs[0].n_views, runs) for (m, _), runs in groups.items()), key=_order)
    ref_times = {e.n_views: e.train_s() for e in entries if e.method == reference}
    notes = []
    if not ref_times:
        notes.append(f"reference {reference} has no runs here: no equal-time column")
    for entry in entries:
        t = ref_times.get(entry.n_views)
        entry.at_ref = equal_time(entry.chosen_runs, t) if t is not None else None
        entry.within_ref = within_time(entry, t) if t is not None else None
    for n_views, t in ref_times.items():
        if t is None:
            notes.append(f"reference {reference} has no finished run with train_s at {n_views} views: "
                         "no equal-time value there")  # fmt: skip
    failed = [r for e in entries for r in e.runs if not r.ok]
    return Leaderboard(entries, reference, ref_times, failed, notes)


@dataclass(frozen=True)
class Lead:
    """The reference's test PSNR lead over the strongest other method at one view count, and the time ratio,
    both on the scenes the two have finished at their chosen budgets."""

    n_views: Any
    reference: Entry | None
    other: Entry | None

    def scenes(self) -> list[str]:
        """The scenes both methods have a test PSNR for at their chosen budgets."""
        if self.reference is None or self.other is None:
            return []
        ours, theirs = (set(scene_means(e.chosen_runs, _test_psnr)) for e in (self.reference, self.other))
        return sorted(ours & theirs)

    def _mean(self, entry: Entry | None, value: Value) -> float | None:
        per_scene = scene_means(entry.chosen_runs, value) if entry is not None else {}
        values = [per_scene[s] for s in self.scenes() if s in per_scene]
        return statistics.fmean(values) if values else None

    def psnr(self) -> tuple[float | None, float | None]:
        """Test PSNR of the reference and of the other method on the shared scenes."""
        return self._mean(self.reference, _test_psnr), self._mean(self.other, _test_psnr)

    def lead_db(self) -> float | None:
        ours, theirs = self.psnr()
        return None if ours is None or theirs is None else ours - theirs

    def times(self) -> tuple[float | None, float | None]:
        """Total training time of the reference and of the other method on the shared scenes."""
        return self._mean(self.reference, Run.total_time), self._mean(self.other, Run.total_time)

    def time_ratio(self) -> float | None:
        ours, theirs = self.times()
        return None if ours is None or not theirs else ours / theirs


def _test_psnr(run: Run) -> float | None:
    return run.test("psnr")


def leads(board: Leaderboard) -> list[Lead]:
    """One :class:`Lead` per view count, against the other method best on the reference's scenes (one that
    covers all of them before one that covers fewer)."""
    out = []
    for n_views in board.views():
        rows = [e for e in board.entries if e.n_views == n_views and e.stat("psnr").mean is not None]
        ref = next((e for e in rows if e.method == board.reference), None)
        candidates = [Lead(n_views, ref, e) for e in rows if e.method != board.reference]
        candidates = [c for c in candidates if ref is None or c.lead_db() is not None]
        if ref is None or not candidates:
            out.append(Lead(n_views, ref, candidates[0].other if candidates else None))
            continue
        ref_scenes = len(scene_means(ref.chosen_runs, _test_psnr))
        out.append(max(candidates, key=lambda c: (len(c.scenes()) == ref_scenes, -(c.lead_db() or 0.0))))
    return out


def lead_text(board: Leaderboard, lead: Lead) -> str:
    """The lead as one sentence."""
    where = f"{lead.n_views} views"
    if lead.reference is None:
        return f"{where}: no lead: {board.reference} has no test PSNR at a chosen budget"
    if lead.other is None:
        return f"{where}: no lead: no other method has a test PSNR at a chosen budget"
    diff, ratio, scenes = lead.lead_db(), lead.time_ratio(), lead.scenes()
    if diff is None:
        return f"{where}: no lead: {board.reference} and {lead.other.method} share no finished scene"
    (ours, theirs), (t_ours, t_theirs) = lead.psnr(), lead.times()
    verb = "leads" if diff >= 0 else "trails"
    text = (f"{where}: {board.reference} {verb} the strongest other method, {lead.other.method}, by "
            f"{diff:+.2f} dB test PSNR ({ours:.2f} vs {theirs:.2f})")  # fmt: skip
    if ratio is not None:
        text += f", at {ratio:.2f}× its training time ({t_ours:.1f} s vs {t_theirs:.1f} s)"
    if len(scenes) < len(board.scenes(lead.n_views)):
        text += f", on the scenes both finished ({', '.join(scenes)})"
    return text + "."


@dataclass(frozen=True)
class FrontSegment:
    """A stretch of the Pareto front over the validation curves held by one method (and its chosen budget):
    its first front point at ``start_s``, its last at ``end_s`` with validation PSNR ``psnr``."""

    method: str
    start_s: float
    end_s: float
    psnr: float


def front_by_time(board: Leaderboard, n_views: Any) -> list[FrontSegment]:
    """Which method is best at every training budget: the Pareto front of the mean validation curves (at the
    chosen budgets; total wall time) at one view count, consecutive points of one method merged."""
    points = [Point(f"{e.method} ({e.budget_label()})", "", t, 0.0, y, 0.0, 1)
              for e in board.entries if e.n_views == n_views for t, y in e.curve() if t > 0]  # fmt: skip
    segments: list[FrontSegment] = []
    for p in pareto_front(points):
        if segments and segments[-1].method == p.row:
            segments[-1] = replace(segments[-1], end_s=p.x, psnr=p.y)
        else:
            segments.append(FrontSegment(p.row, p.x, p.x, p.y))
    return segments


def front_text(board: Leaderboard, n_views: Any) -> str:
    """The front as one line: ``from 1.0 s A (19.70 dB at 5.6 s) · from 5.6 s B ...``."""
    segments = front_by_time(board, n_views)
    if not segments:
        return f"{n_views} views: no validation curve"
    parts = [f"from {s.start_s:.1f} s {s.method} ({s.psnr:.2f} dB at {s.end_s:.1f} s)" for s in segments]
    return f"{n_views} views: " + " · ".join(parts)


# -- Markdown -------------------------------------------------------------------------------------


def _fmt(value: float | None, decimals: int) -> str:
    return DASH if value is None else f"{value:.{decimals}f}"


def _fmt_stat(stat: Stat, decimals: int) -> str:
    text = _fmt(stat.mean, decimals)
    return text + (f" ± {stat.std:.{decimals}f}" if stat.mean is not None and stat.std is not None else "")


def _refs(board: Leaderboard, runs: Iterable[Run]) -> str:
    numbers = [board.footnote(r) for r in runs if not r.ok]
    return f"[{','.join(map(str, numbers))}]" if numbers else ""


def _budget_cell(board: Leaderboard, entry: Entry) -> str:
    if entry.chosen is None:
        return DASH + _refs(board, entry.runs)
    its = entry.iterations()
    return entry.budget_label() + (f" ({its[0]} it)" if len(its) == 1 and entry.chosen.key != "iterations" else "")


def _scores_cell(board: Leaderboard, entry: Entry) -> str:
    """Each budget's score, the chosen one in bold; a budget scored on fewer seeds or scenes than another says
    on which (its cell is then not comparable with the others': the notes give the pairwise comparisons)."""
    parts = []
    most_seeds = max((len(s.seeds) for s in entry.scores.values()), default=0)
    most_scenes = max((len(s.scenes) for s in entry.scores.values()), default=0)
    for budget, score in entry.scores.items():
        refs = _refs(board, (r for r in entry.runs if r.budget == budget)) if score.score is None else ""
        fewer = [f"seed {', '.join(sorted(score.seeds, key=sort_key))}"] if 0 < len(score.seeds) < most_seeds else []
        fewer += [f"{len(score.scenes)} of {most_scenes} scenes"] if 0 < len(score.scenes) < most_scenes else []
        on = " (" + "; ".join(fewer) + ")" if fewer else ""
        text = f"{budget.label()}: {_fmt(score.score, 2)}{on}{refs}"
        parts.append(f"**{text}**" if budget == entry.chosen else text)
    return " · ".join(parts)


def _at_ref_cell(entry: Entry) -> str:
    if entry.at_ref is None or entry.at_ref.value is None:
        return DASH
    return f"{entry.at_ref.value:.2f}" + (PAST_END if entry.at_ref.past_end else "")


def _within_ref_cell(entry: Entry) -> str:
    w = entry.within_ref
    if w is None or w.test_psnr.mean is None:
        return DASH
    return f"{_fmt_stat(w.test_psnr, 2)} ({w.budget.label()})"


def _runs_cell(entry: Entry) -> str:
    runs = entry.chosen_runs if entry.chosen else entry.runs
    failed = sum(r.record.status == "failed" for r in runs)
    unfinished = sum(r.record.status in ("running", "interrupted") for r in runs)
    return f"{len(runs)} / {failed}" + (f" ({unfinished} unfinished)" if unfinished else "")


def _scenes_cell(board: Leaderboard, entry: Entry) -> str:
    done = scene_means(entry.chosen_runs, _test_psnr) if entry.chosen else {}
    return f"{len(done)}/{len(board.scenes(entry.n_views))}"


def _md_row(cells: Sequence[str]) -> str:
    return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"


def main_table(board: Leaderboard) -> list[str]:
    """The leaderboard table (Markdown lines), ranked per view count by test PSNR at the chosen budget."""
    header = ["rank", "method", "views", "budget", "val PSNR by budget (selection)", "test PSNR ↑", "test SSIM ↑",
              "train time [s] ↓", "val PSNR @ ref. time ↑", "test PSNR within ref. time ↑", "scenes",
              "runs / failed"]  # fmt: skip
    lines = [_md_row(header), "|" + "|".join("---" for _ in header) + "|"]
    rank: dict[str, int] = defaultdict(int)
    for e in board.entries:
        ranked, views = e.stat("psnr").mean is not None, json.dumps(e.n_views, default=str)
        rank[views] += ranked
        cells = [str(rank[views]) if ranked else DASH, e.method, str(e.n_views), _budget_cell(board, e),
                 _scores_cell(board, e), _fmt_stat(e.stat("psnr"), 2), _fmt_stat(e.stat("ssim"), 3),
                 _fmt(e.train_s(), 1), _at_ref_cell(e), _within_ref_cell(e), _scenes_cell(board, e),
                 _runs_cell(e)]  # fmt: skip
        lines.append(_md_row(cells))
    return lines


def legend(board: Leaderboard) -> str:
    """What the columns of :func:`main_table` mean."""
    times = ", ".join(f"{v} views {t:.1f} s" for v, t in board.ref_times.items() if t is not None) or "none"
    return (
        f"budget: {LARGEST} = the largest budget tried was chosen (a larger one was not tried: the row may sit "
        "below the method's converged one). "
        "test PSNR / SSIM: mean over scenes at the chosen budget, ± std over seeds of the scene mean (≥ 2 seeds). "
        "train time: train_s + stage1_train_s (+ capacity_search_s), mean over scenes. "
        f"val PSNR @ ref. time: validation PSNR at {board.reference}'s mean total training time ({times}), "
        f"linearly interpolated on each run's curve (first stage added), per scene, then averaged; {PAST_END} = "
        f"a run had already ended (its last value); {DASH} = the time is before a curve's first point. "
        "test PSNR within ref. time: at the best of the method's budgets (chosen on validation views, as the board "
        "chooses) whose total training time is at most that time, with that budget; "
        f"{DASH} = no budget tried fits. "
        "scenes: with a test PSNR at the chosen budget, of those run at this view count (rows over fewer scenes "
        "average fewer, possibly easier, scenes). runs / failed: at the chosen budget. [n]: failed or unfinished "
        "runs, listed below."
    )


def scene_table(board: Leaderboard, n_views: Any) -> list[str]:
    """Test PSNR per scene at each method's chosen budget (mean over seeds), for one view count."""
    scenes = board.scenes(n_views)
    lines = [_md_row(["method", "budget", *scenes]), "|" + "|".join("---" for _ in range(2 + len(scenes))) + "|"]
    for e in (e for e in board.entries if e.n_views == n_views):
        runs = e.chosen_runs if e.chosen else e.runs
        means = scene_means(runs, _test_psnr) if e.chosen else {}
        cells = []
        for scene in scenes:
            here = [r for r in runs if r.scene == scene]
            cells.append(f"{means[scene]:.2f}" if scene in means else DASH + _refs(board, here))
        lines.append(_md_row([e.method, _budget_cell(board, e), *cells]))
    return lines


def _footnote_lines(board: Leaderboard) -> list[str]:
    lines = []
    for i, run in enumerate(board.footnotes, 1):
        message = run.record.message()
        what = f"{run.record.status}: {message}" if message else run.record.status
        lines.append(f"[{i}] {run.method}, {run.n_views} views, {run.budget.label()}, scene={run.scene}, "
                     f"seed={run.seed} — {what} — {run.record.run_dir}")  # fmt: skip
    return lines


def render_markdown(board: Leaderboard) -> str:
    """``leaderboard.md``: the table, the selection rule, the lead, per-scene tables, footnotes and notes."""
    out = ["### Leaderboard: every method at its own best budget, chosen on validation views", "", *main_table(board),
           "", f"Selection rule: {SELECTION_RULE}", "", legend(board), "", "**Lead:**", ""]  # fmt: skip
    out += [f"- {lead_text(board, lead)}" for lead in leads(board)] + [""]
    out += ["**Best by training time** (the Pareto front of the validation curves: the method with the highest "
            "validation PSNR reached by that total wall time, at its chosen budget):", ""]  # fmt: skip
    out += [f"- {front_text(board, n_views)}" for n_views in board.views()] + [""]
    for n_views in board.views():
        title = f"### Test PSNR per scene at the chosen budgets ({n_views} views)"
        out += [title, "", *scene_table(board, n_views), ""]
    footnotes = _footnote_lines(board)
    if footnotes:
        out += [f"**Failed / unfinished runs ({len(footnotes)}):**", "", *(f"- {line}" for line in footnotes), ""]
    notes = list(board.notes) + [f"{e.method} ({e.n_views} views): {n}" for e in board.entries for n in e.notes]
    if notes:
        out += ["**Notes:**", "", *(f"- {n}" for n in dict.fromkeys(notes)), ""]
    return "\n".join(out).rstrip() + "\n"


# -- JSON -----------------------------------------------------------------------------------------


def _stat_json(stat: Stat) -> dict[str, Any]:
    return {"mean": stat.mean, "std": stat.std, "n_seeds": stat.n_seeds}


def _budget_json(budget: Budget | None, entry: Entry) -> dict[str, Any] | None:
    if budget is None:
        return None
    value: float | int | None = budget.value if math.isfinite(budget.value) else None
    if value is not None and float(value).is_integer():
        value = int(value)
    return {"key": budget.key or None, "value": value, "label": budget.label(), "iterations": entry.iterations()}


def _within_json(entry: Entry) -> dict[str, Any] | None:
    w = entry.within_ref
    if w is None:
        return None
    return {"time_s": w.time_s, "budget": w.budget.label(), "val_psnr": w.val_psnr,
            "test_psnr": _stat_json(w.test_psnr), "train_s": w.train_s}  # fmt: skip


def entry_json(board: Leaderboard, entry: Entry) -> dict[str, Any]:
    """One method's leaderboard data as plain JSON values."""
    scores = {b.name(): {"val_psnr": s.score, "scenes": list(s.scenes), "seeds": sorted(s.seeds, key=sort_key),
                         "runs": s.n_runs, "failed": s.n_failed,
                         "unfinished": s.n_unfinished, "ok_without_val_curve": s.n_no_val}
              for b, s in entry.scores.items()}  # fmt: skip
    at = entry.at_ref
    return {
        "method": entry.method, "n_views": entry.n_views, "chosen_budget": _budget_json(entry.chosen, entry),
        "chosen_is_largest_tried": entry.chose_largest(), "val_psnr": entry.val_score(),
        "val_psnr_by_budget": scores,
        "test_psnr": _stat_json(entry.stat("psnr")), "test_ssim": _stat_json(entry.stat("ssim")),
        "train_s": entry.train_s(),
        "equal_time_val_psnr": None if at is None else {"time_s": at.time_s, "value": at.value,
                                                         "past_end": at.past_end},
        "within_ref_time": _within_json(entry),
        "test_psnr_per_scene": scene_means(entry.chosen_runs, _test_psnr) if entry.chosen else {},
        "failed_runs": [board.footnote(r) for r in entry.runs if not r.ok], "notes": entry.notes,
    }  # fmt: skip


def to_json(board: Leaderboard) -> dict[str, Any]:
    """``leaderboard.json``: the selection rule, the reference, every method, the leads and failed runs."""
    lead_rows = [{"n_views": lead.n_views, "other": lead.other.method if lead.other else None,
                  "lead_db": lead.lead_db(), "time_ratio": lead.time_ratio(), "text": lead_text(board, lead)}
                 for lead in leads(board)]  # fmt: skip
    failed = [{"n": i, "method": r.method, "status": r.record.status, "reason": r.record.message() or None,
               "run_dir": r.record.run_dir} for i, r in enumerate(board.footnotes, 1)]  # fmt: skip
    return {
        "selection_rule": SELECTION_RULE,
        "reference": {"method": board.reference,
                      "train_s": {str(v): t for v, t in board.ref_times.items()}},
        "methods": [entry_json(board, e) for e in board.entries],
        "lead": lead_rows,
        "front_by_time": {str(v): [{"method": s.method, "from_s": s.start_s, "to_s": s.end_s, "val_psnr": s.psnr}
                                   for s in front_by_time(board, v)] for v in board.views()},
        "failed_runs": failed, "notes": board.notes,
    }  # fmt: skip


# -- figure ---------------------------------------------------------------------------------------


def draw_curves(board: Leaderboard, out_dir: Path) -> list[Path]:
    """``leaderboard_curves.{png,svg}``: mean validation PSNR against total wall time at the chosen budgets,
    one panel per view count, with the Pareto front over every method's points as a thick grey staircase."""
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    from src.reporting.chart import _natural, _save, _Style

    style = _Style.of(sorted({e.method for e in board.entries}, key=_natural), [])
    views = board.views() or [None]
    fig = Figure(figsize=(max(7.5, 1.5 + 5.0 * len(views)), 5.2), layout="constrained")
    for ax, n_views in zip(fig.subplots(1, len(views), squeeze=False)[0], views, strict=True):
        _draw_panel(ax, board, n_views, style)
    drawn = {e.method: e.budget_label() for e in board.entries if e.chosen and e.curve()}
    handles = [Line2D([], [], color=style.colour(m, ""), marker=style.marker(m), label=f"{m} ({drawn[m]})")
               for m in style.methods if m in drawn]  # fmt: skip
    handles.append(Line2D([], [], color="0.55", lw=6, alpha=0.45, label="Pareto front (best PSNR by this time)"))
    handles.append(Line2D([], [], color="0.3", ls=":", lw=1, label=f"{board.reference} mean training time"))
    fig.legend(handles=handles, loc="outside lower center", ncols=min(3, len(handles)), fontsize=8)
    fig.suptitle("Every method at its own best budget (chosen on validation views)\n"
                 "validation PSNR against training wall time, mean over scenes and seeds", fontsize=9)  # fmt: skip
    return _save(fig, out_dir, "leaderboard_curves")


def _draw_panel(ax: Any, board: Leaderboard, n_views: Any, style: Any) -> None:
    from src.reporting.chart import _log_time_axis

    _log_time_axis(ax)
    ax.grid(True, which="major", alpha=0.3)
    ax.set_xlabel("training wall time [s] (log; incl. first stage)", fontsize=8)
    ax.set_ylabel("validation PSNR (↑)")
    ax.set_title(f"{n_views} views", fontsize=10)
    points = []
    for entry in (e for e in board.entries if e.n_views == n_views):
        curve = [(t, y) for t, y in entry.curve() if t > 0]
        if not curve:
            continue
        points += curve
        label = entry.budget_label()
        ax.plot([t for t, _ in curve], [y for _, y in curve], color=style.colour(entry.method, ""), lw=1.2,
                marker=style.marker(entry.method), markersize=4, zorder=3, label=f"{entry.method} {label}")  # fmt: skip
    if not points:
        ax.text(0.5, 0.5, "no validation curve yet", ha="center", va="center", transform=ax.transAxes)
        return
    front = pareto_staircase(points)
    xs, ys = [p[0] for p in front], [p[1] for p in front]
    xs.append(max(t for t, _ in points))
    ys.append(ys[-1])
    ax.step(xs, ys, where="post", color="0.55", lw=6, alpha=0.45, zorder=1, solid_capstyle="butt")
    t_ref = board.ref_times.get(n_views)
    if t_ref:
        ax.axvline(t_ref, color="0.3", ls=":", lw=1, zorder=2)


# -- output and command line ----------------------------------------------------------------------


def write_leaderboard(board: Leaderboard, out_dir: Path) -> list[Path]:
    """Write ``leaderboard.md``, ``leaderboard.json`` and the curves figure into ``out_dir`` (caller holds its lock)."""
    md, js = out_dir / "leaderboard.md", out_dir / "leaderboard.json"
    atomic_write_text(md, render_markdown(board))
    atomic_write_text(js, json.dumps(to_json(board), indent=2, allow_nan=False, ensure_ascii=False, default=str) + "\n")
    return [md, js, *draw_curves(board, out_dir)]


def method_names(records: Iterable[RunRecord]) -> list[str]:
    """The method labels present (what ``--reference`` may name)."""
    return sorted({method_label(r) for r in records})


def leaderboard_cli(collection: Collection, out: Path | None, reference: str | None) -> int:
    """``--leaderboard``: print the board; with ``out`` also write its files there. Returns the exit code."""
    names = method_names(collection.records)
    if reference is not None and reference not in names:
        return cli_error(f"--reference {reference}: no run of that method; experiments present: {', '.join(names)}")
    board = build_leaderboard(collection.records, reference or DEFAULT_REFERENCE)
    text = render_markdown(board)
    if out is None:
        print(text, end="")
        return 0
    try:
        with output_lock(out, "choose another --out"):
            print(text, end="")
            for path in [*write_leaderboard(board, out), write_archive(collection.records, out)]:
                print(f"wrote {path}", file=sys.stderr)
    except OutputBusy as exc:
        return cli_error(str(exc))
    except OSError as exc:
        return cli_error(f"cannot write the output: {os_error_line(exc)}")
    return 0
