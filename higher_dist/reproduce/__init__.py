"""`higher-reproduce`: the paper's experiments as one resumable plan of runs, its figures and its table.

plan.py      which runs each experiment needs, their flags, their state on disk, the cost estimate
executor.py  runs the plan (parallel, skip finished, resume interrupted) with a progress view
gen_task.py  one `generator` run: exact match vs expert pairs (the generator benchmark's path)
figures.py   the paper's figures from a plan's folder (mean and one std over seeds)
claims.py    results.md: each claim of the paper, ours, a verdict
cli.py       the command line
"""
