"""A plan's finished runs, small enough to keep in git: `higher-reproduce --archive DEST --out DIR`.

A plan that outlives the machine it ran on (a session, a lease, a node) keeps its results here and
nothing else: the checkpoints, the replay and the logs stay behind. DEST is itself a plan folder:
`--report --out DEST` draws the same figures and tables as DIR would, and a copy of DEST resumes the
plan (`cp -r DEST DIR` then the plan's own command: the archived runs read as done, the rest run).

What a finished run keeps:
- config.json (the resolved config; the report reads the replay's capacity from it);
- result.json of a generator run, as it is;
- metrics.jsonl thinned: the first and the last record, every record whose greedy evaluation
  differs from the record before (so every end point and every evaluation curve is exactly the run's),
  every record of the first START_FRAMES frames (the replay's composition "at the start"), and between
  them one record per THIN_FRAMES env frames and at least one per THIN_SECONDS (the training curves and
  the run's pace at that resolution). The per-process liveness (`roles`) is left out: it describes the machine, not the result.
An unfinished run is not archived: without its checkpoint it could not resume anyway.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

from higher_dist import metrics as m
from higher_dist.analysis.runs import is_number
from higher_dist.reproduce.plan import Plan
from higher_dist.reproduce.replay_claims import START_FRAMES
from higher_dist.reproduce.status import MAX_GAP_S, run_state
from higher_dist.rundir import atomic_write_bytes, read_metrics

THIN_FRAMES = 10_000  # 200 points on a 2M-frame curve
THIN_SECONDS = MAX_GAP_S / 2  # a slow run keeps a record this often: the pace measure counts longer gaps as stops
DROPPED_KEYS = ("roles",)
EVAL_KEYS = (m.EVAL_FRAMES, m.SUCCESS_EVAL_TRAIN, m.SUCCESS_EVAL_HELDOUT, m.SUCCESS_EVAL_TRAIN_AVERAGED,
             m.SUCCESS_EVAL_HELDOUT_AVERAGED)  # a change in any of them is an evaluation's result
KEPT_FILES = ("config.json", "result.json")


def thin_records(records: list[dict], every: int = THIN_FRAMES) -> list[dict]:
    """The records an archived run keeps (see the module's docstring), in their order."""
    kept: list[dict] = []
    next_frames, next_time, previous_eval = 0.0, float("-inf"), None
    for i, record in enumerate(records):
        frames, when = record.get(m.FRAMES), record.get(m.TIME)
        evaluated = tuple(record.get(k) for k in EVAL_KEYS)
        new_eval = evaluated != previous_eval  # every record repeats the latest evaluation
        on_step = is_number(frames) and (frames >= next_frames or frames <= START_FRAMES)
        overdue = is_number(when) and when >= next_time
        if i == 0 or i == len(records) - 1 or new_eval or on_step or overdue:
            kept.append({k: v for k, v in record.items() if k not in DROPPED_KEYS})
            if is_number(frames):
                next_frames = (frames // every + 1) * every
            if is_number(when):
                next_time = when + THIN_SECONDS
        previous_eval = evaluated
    return kept


def archive(plan: Plan, dest: Path) -> list[str]:
    """Write the finished runs of `plan` and its plan.json to `dest`; returns the names archived.
    A run already in `dest` is rewritten (its source is the newer)."""
    dest = Path(dest)
    if dest.resolve() == plan.out.resolve():
        raise ValueError(f"--archive {dest}: must differ from --out")
    dest.mkdir(parents=True, exist_ok=True)
    names = []
    for run in plan.runs:
        source = plan.path(run)
        if run_state(run, source) != "done":
            continue
        target = dest / "runs" / run.name
        target.mkdir(parents=True, exist_ok=True)
        for name in KEPT_FILES:
            if (source / name).exists():
                shutil.copyfile(source / name, target / name)
        if run.kind == "cluster":
            kept = thin_records(read_metrics(source / "metrics.jsonl"))
            atomic_write_bytes(target / "metrics.jsonl",
                               "".join(json.dumps(r, separators=(",", ":")) + "\n" for r in kept).encode())
        names.append(run.name)
    atomic_write_bytes(dest / "plan.json", (plan.out / "plan.json").read_bytes())
    return names
