"""`higher-bench all` (what `make bench` runs): every benchmark in its own process, one after another,
each one's readable output passed through, its last-line JSON saved to RESULTS/NAME.json, and a
summary table of the headline figures against the targets listed in docs/benchmarks.md at the end."""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

# (name, argv, [(label, key, target or None)]); a negative target is an upper bound (-3: at most 3).
PLAN = [
    ("world", ["world"], [("world steps/s, B=64", "b64_steps_per_s", 50_000),
                          ("world / minigrid, B=64", "ratio_b64", 20)]),
    ("learner", ["learner"], [("learner updates/s, B=64", "b64_updates_per_s", None),
                              ("learner samples/s, B=64", "b64_samples_per_s", None),
                              ("learner samples/s, B=256", "b256_samples_per_s", 25_000),
                              ("learner share of compute bound", "bound_ratio", 0.5)]),
    ("checkpoint", ["checkpoint"], [("checkpoint MiB, full replay", "size_mib", None),
                                    ("checkpoint pause s", "pause_s", None)]),
    ("wire", ["wire"], [("wire episodes/s, PUSH/PULL", "pushpull_episodes_per_s", None)]),
    ("generator", ["generator", "--pairs", "5000"], [("generator seen exact match", "seen_exact_match", 0.9),
                                                     ("generator unseen exact match", "unseen_exact_match", 0.8)]),
    ("cluster", ["cluster", "--seconds", "60"], [("cluster env frames/s", "frames_per_s", 2500),
                                                 ("cluster updates/s", "updates_per_s", None),
                                                 ("cluster samples/frame", "samples_per_frame", None),
                                                 ("learner_ratio", "learner_ratio", 0.8)]),
    # The longest: one her run until 40% and 60% (the mean of three evaluations), 25 minutes at most.
    ("time-to-success", ["time-to-success", "--preset", "her", "--targets", "0.4", "0.6", "--max-minutes", "25"],
     [("her minutes to 40%", "minutes_to_40", -3), ("her minutes to 60%", "minutes_to_60", -15)]),
]


def run_one(argv: list[str]) -> dict | None:
    cmd = [sys.executable, "-c", "import sys; from higher_dist.bench import main; sys.exit(main(sys.argv[1:]))", *argv]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    last = ""
    assert proc.stdout is not None
    for line in proc.stdout:
        print(line, end="", flush=True)
        if line.strip():
            last = line.strip()
    proc.wait()
    try:
        return json.loads(last) if proc.returncode == 0 else None
    except json.JSONDecodeError:
        return None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser("higher-bench all")
    p.add_argument("--results", default="results", help="folder for NAME.json files")
    p.add_argument("--only", nargs="*", default=None, help="run only these benchmarks")
    args = p.parse_args(argv)
    out = Path(args.results)
    out.mkdir(parents=True, exist_ok=True)
    summary, failed = [], []
    for name, bench_argv, keys in PLAN:
        if args.only and name not in args.only:
            continue
        print(f"\n=== higher-bench {' '.join(bench_argv)} ===", flush=True)
        t0 = time.time()
        result = run_one(bench_argv)
        if result is None:
            failed.append(name)
            continue
        result["bench_wall_s"] = round(time.time() - t0, 1)
        (out / f"{name}.json").write_text(json.dumps(result, indent=2))
        for label, key, target in keys:
            value = result.get(key)
            if target is None:
                verdict = ""
            elif value is None:
                verdict = "SHORT" if target < 0 else ""
            else:
                verdict = "meets" if (value <= -target if target < 0 else value >= target) else "SHORT"
            summary.append((label, value, target, verdict))
    print("\nsummary (this machine)")
    print(f"{'figure':<34}{'value':>14}{'target':>12}  verdict")
    for label, value, target, verdict in summary:
        v = "-" if value is None else (f"{value:,.3f}" if isinstance(value, float) and value < 10 else f"{value:,.0f}")
        t = "" if target is None else (f"<= {-target:,}" if target < 0 else f">= {target:,}")
        print(f"{label:<34}{v:>14}{t:>12}  {verdict}")
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
    print(json.dumps({"results": str(out), "failed": failed,
                      "summary": {label: value for label, value, _, _ in summary}}))
    return 1 if failed else 0
