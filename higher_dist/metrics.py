"""The names of every metric a run reports, in one place, with what each means.

The learner's record (metrics.jsonl, telemetry, TensorBoard), the single-process runner, the dashboard,
`higher-plot` and the end-of-run summary all use these names, so a renamed metric cannot silently
disappear from one of them. Pure: no sockets, no rich.
"""
from __future__ import annotations

# -- progress -------------------------------------------------------------------------------------
FRAMES = "frames"  # env frames of original episodes the learner took in (the run's clock)
FRAMES_BUDGET = "frames_budget"
UPDATES = "updates"
EPISODES = "episodes"
ELAPSED_S = "elapsed_s"  # the run's running time in seconds, carried across resumes
PRESET = "preset"
WORLD = "world"
FRAMES_PER_S = "frames_per_s"
UPDATES_PER_S = "updates_per_s"
WEIGHTS_VERSION = "weights_version"
WEIGHTS_LAG_MEAN = "weights_lag_mean"
EPSILON_MEAN = "epsilon_mean"

# -- success --------------------------------------------------------------------------------------
# Greedy evaluation (epsilon 0, one episode per environment) is the headline; training success mixes
# environments exploring at their epsilons and is reported as such.
SUCCESS_EVAL_TRAIN = "success_rate_eval_train"
SUCCESS_EVAL_HELDOUT = "success_rate_eval_heldout"
SUCCESS_TRAIN = "success_rate_train"
EVAL_FRAMES = "eval_frames"  # env frames the evaluated weights had seen (every record repeats the latest)
SE_SUFFIX = "_se"  # + on an eval key: its standard error, sqrt(p (1 - p) / episodes)
EVAL_KEYS = (SUCCESS_EVAL_TRAIN, SUCCESS_EVAL_HELDOUT, SUCCESS_EVAL_TRAIN + SE_SUFFIX,
             SUCCESS_EVAL_HELDOUT + SE_SUFFIX)
# With dqn.average_tau > 0 the same evaluation (same goals) also scores the moving average of the
# online weights, under the same names + this suffix (before any _se).
AVERAGED_SUFFIX = "_averaged"
SUCCESS_EVAL_TRAIN_AVERAGED = SUCCESS_EVAL_TRAIN + AVERAGED_SUFFIX
SUCCESS_EVAL_HELDOUT_AVERAGED = SUCCESS_EVAL_HELDOUT + AVERAGED_SUFFIX

# -- replay and learning --------------------------------------------------------------------------
REPLAY_SIZE = "replay_size"
REPLAY_RATIO = "replay_ratio"
RELABELLED_EPISODES = "relabelled_episodes"
REPLAY_ORIGIN_PREFIX = "replay_"  # + success | wrong_pick | timeout | relabelled
# The DQN step's own metrics (learning/dqn.py), carried into the record as they come.
LOSS = "loss"
Q_MEAN = "q_mean"
TD_ABS_MEAN = "td_abs_mean"
TARGET_MEAN = "target_mean"
GRAD_NORM = "grad_norm"
LEARNING_RATE = "learning_rate"  # the optimiser's, as of the last update (dqn.lr_decay_frames)
SKIPPED_UPDATES = "skipped_updates"  # steps refused for a non-finite gradient
LOSS_COMPILED = "loss_compiled"  # 1 once the update runs the torch.compile'd loss
COMPILE_PENDING = "compile_pending"  # 1 while that compile runs in the background (updates run eager)

# -- relabelling ----------------------------------------------------------------------------------
RELABEL_STRATEGY = "relabel_strategy"
GENERATOR_VAL_ACCURACY = "generator_val_accuracy"  # as of its latest evaluation (None before the first)
GENERATOR_VAL_AT_PAIRS = "generator_val_at_pairs"  # dataset size at that evaluation
RELABEL_DATASET_SIZE = "relabel_dataset_size"
RELABEL_GATE_OPEN = "relabel_gate_open"
RELABEL_ACCURACY = "relabel_accuracy"  # over the last relabel.RECENT_RELABELS relabels
RELABEL_ACCURACY_TOTAL = "relabel_accuracy_total"  # since the start of the run
RELABEL_UNPARSEABLE = "relabel_unparseable"
RELABEL_CONTRADICTING = "relabel_contradicting"  # learned relabels naming the failed goal, dropped
GENERATOR_LOSS = "generator_loss"
RELABELS_PER_S = "relabels_per_s"

# -- health ---------------------------------------------------------------------------------------
REJECTED = "rejected_messages"  # every role's dropped messages, summed
LEARNER_REJECTED = "learner_rejected"
REJECTS_BY_REASON = "rejects_by_reason"  # {reason: count} over all roles
HANDLER_ERRORS = "handler_errors"  # messages whose handling raised unexpectedly (logged, loop went on)
ROLES = "roles"

LABELS: dict[str, str] = {
    FRAMES: "env frames",
    SUCCESS_EVAL_TRAIN: "greedy success, training goals",
    SUCCESS_EVAL_HELDOUT: "greedy success, held-out goals",
    SUCCESS_TRAIN: "training success (exploring, epsilon-greedy)",
    SUCCESS_EVAL_TRAIN_AVERAGED: "greedy success of the averaged weights, training goals",
    SUCCESS_EVAL_HELDOUT_AVERAGED: "greedy success of the averaged weights, held-out goals",
    GENERATOR_VAL_ACCURACY: "generator exact match (validation)",
    RELABEL_ACCURACY: "relabel accuracy (last 1000 relabels)",
    RELABEL_DATASET_SIZE: "generator pairs",
    RELABEL_GATE_OPEN: "generator gate open",
    REPLAY_RATIO: "samples per insert",
    FRAMES_PER_S: "env frames/s",
    UPDATES_PER_S: "updates/s",
    REJECTED: "rejected messages",
}


def label(name: str) -> str:
    """A human label for a metric name (the name itself where none is declared)."""
    return LABELS.get(name, name.replace("_", " "))


def replay_origin(origin: str) -> str:
    return REPLAY_ORIGIN_PREFIX + origin


def relabel_record(strategy_metrics: dict) -> dict:
    """The record's relabelling fields from a relabel strategy's `metrics()`: the same keys whether the
    strategy runs in the single-process runner or in the relabeler service."""
    s = strategy_metrics
    return {
        RELABEL_STRATEGY: s.get("strategy"), GENERATOR_VAL_ACCURACY: s.get("val_accuracy"),
        RELABEL_DATASET_SIZE: s.get("dataset_size"), RELABEL_GATE_OPEN: s.get("gate_open"),
        GENERATOR_VAL_AT_PAIRS: s.get("val_at_pairs"),
        RELABEL_ACCURACY: s.get("relabel_accuracy"), RELABEL_ACCURACY_TOTAL: s.get("relabel_accuracy_total"),
        RELABEL_UNPARSEABLE: s.get("unparseable"), RELABEL_CONTRADICTING: s.get("contradicting"),
        GENERATOR_LOSS: s.get("loss"),
    }
