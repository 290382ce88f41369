"""The names of every metric a run reports, in one place, with what each means.

The learner's record (metrics.jsonl, telemetry, TensorBoard), the single-process runner, the dashboard,
`higher-plot` and the end-of-run summary all use these names, so a renamed metric cannot silently
disappear from one of them. Pure: no sockets, no rich.
"""
from __future__ import annotations

# Every key has one comment: its meaning, then its unit in [brackets]. docs/metrics.md is generated from
# these (`make docs`). A record is one line of metrics.jsonl (and one telemetry message, one TensorBoard step).

# -- progress -------------------------------------------------------------------------------------
TIME = "time"  # when the record was written (Unix time) [s]
FRAMES = "frames"  # env frames of original episodes the learner took in: the run's clock [frames]
FRAMES_BUDGET = "frames_budget"  # the run's frame budget (`frames` in the config) [frames]
UPDATES = "updates"  # DQN updates done [count]
EPISODES = "episodes"  # original episodes the learner took in [count]
ELAPSED_S = "elapsed_s"  # the run's running time, carried across resumes [s]
PRESET = "preset"  # the paper's method this run is [name]
WORLD = "world"  # the world's name [name]
LAYOUT = "layout"  # how the learner's host shares its cores between the roles (launch/layout.py), as text
FRAMES_PER_S = "frames_per_s"  # env frames per second, summed over live actors [frames/s]
UPDATES_PER_S = "updates_per_s"  # DQN updates per second [1/s]
WEIGHTS_VERSION = "weights_version"  # the version of the weights last published (its update count) [count]
WEIGHTS_LAG_MEAN = "weights_lag_mean"  # how many updates behind the actors' weights are, on average [updates]
EPSILON_MEAN = "epsilon_mean"  # mean exploration epsilon over the actors' environments [probability]

# -- success --------------------------------------------------------------------------------------
# Greedy evaluation (epsilon 0, one episode per environment) is the headline; training success mixes
# environments exploring at their epsilons and is reported as such.
SUCCESS_EVAL_TRAIN = "success_rate_eval_train"  # greedy success on training goals, latest evaluation [fraction]
SUCCESS_EVAL_HELDOUT = "success_rate_eval_heldout"  # greedy success on held-out goals, latest evaluation [fraction]
SUCCESS_TRAIN = "success_rate_train"  # success of the episodes the learner took in, while exploring [fraction]
EVAL_FRAMES = "eval_frames"  # env frames the evaluated weights had seen (every record repeats the latest) [frames]
SE_SUFFIX = "_se"  # + on an evaluation key: its standard error, sqrt(p (1 - p) / episodes) [fraction]
EVAL_KEYS = (SUCCESS_EVAL_TRAIN, SUCCESS_EVAL_HELDOUT, SUCCESS_EVAL_TRAIN + SE_SUFFIX,
             SUCCESS_EVAL_HELDOUT + SE_SUFFIX)
# With dqn.average_tau > 0 the same evaluation (same goals) also scores the moving average of the
# online weights, under the same names + this suffix (before any _se).
AVERAGED_SUFFIX = "_averaged"  # + on an evaluation key: the same evaluation of the averaged weights [fraction]
SUCCESS_EVAL_TRAIN_AVERAGED = SUCCESS_EVAL_TRAIN + AVERAGED_SUFFIX
SUCCESS_EVAL_HELDOUT_AVERAGED = SUCCESS_EVAL_HELDOUT + AVERAGED_SUFFIX

# -- replay and learning --------------------------------------------------------------------------
REPLAY_SIZE = "replay_size"  # transitions in the replay [transitions]
REPLAY_RATIO = "replay_ratio"  # samples drawn per insert so far (the rate limiter's measure) [samples/insert]
RELABELLED_EPISODES = "relabelled_episodes"  # relabelled copies the learner took in [count]
REPLAY_ORIGIN_PREFIX = "replay_"  # + success, wrong_pick, timeout or relabelled: transitions by origin [transitions]
# The DQN step's own metrics (learning/dqn.py), carried into the record as they come.
LOSS = "loss"  # DQN loss of the last update (Huber, importance-weighted) [loss]
Q_MEAN = "q_mean"  # mean Q of the actions taken, last batch [return]
TD_ABS_MEAN = "td_abs_mean"  # mean |TD error|, last batch [return]
TARGET_MEAN = "target_mean"  # mean n-step target, last batch [return]
GRAD_NORM = "grad_norm"  # gradient norm before clipping, last update [norm]
LEARNING_RATE = "learning_rate"  # the optimiser's, as of the last update (dqn.lr_decay_frames) [lr]
SKIPPED_UPDATES = "skipped_updates"  # steps refused for a non-finite gradient [count]
LOSS_COMPILED = "loss_compiled"  # 1 once the update runs the torch.compile'd loss [flag]
COMPILE_PENDING = "compile_pending"  # 1 while that compile runs in the background (updates run eager) [flag]

# -- relabelling ----------------------------------------------------------------------------------
RELABEL_STRATEGY = "relabel_strategy"  # what relabels wrong picks: none, expert, noisy or learned [name]
GENERATOR_VAL_ACCURACY = "generator_val_accuracy"  # generator exact match on its validation pairs, latest [fraction]
GENERATOR_VAL_AT_PAIRS = "generator_val_at_pairs"  # dataset size at that evaluation [pairs]
RELABEL_DATASET_SIZE = "relabel_dataset_size"  # (view, instruction) pairs in the generator's dataset [pairs]
RELABEL_GATE_OPEN = "relabel_gate_open"  # whether the generator relabels yet (enough pairs and accuracy) [flag]
RELABEL_ACCURACY = "relabel_accuracy"  # relabels that name the picked object, last relabel.RECENT_RELABELS [fraction]
RELABEL_ACCURACY_TOTAL = "relabel_accuracy_total"  # the same since the start of the run [fraction]
RELABEL_UNPARSEABLE = "relabel_unparseable"  # generated instructions the grammar cannot parse, dropped [count]
RELABEL_CONTRADICTING = "relabel_contradicting"  # learned relabels naming the failed goal, dropped [count]
GENERATOR_LOSS = "generator_loss"  # the generator's training loss, last update [loss]
RELABELS_PER_S = "relabels_per_s"  # relabelled copies made per second [1/s]

# -- health ---------------------------------------------------------------------------------------
REJECTED = "rejected_messages"  # every role's dropped messages, summed [count]
LEARNER_REJECTED = "learner_rejected"  # messages the learner dropped [count]
REJECTS_BY_REASON = "rejects_by_reason"  # dropped messages over all roles, by reason [{reason: count}]
HANDLER_ERRORS = "handler_errors"  # messages whose handling raised unexpectedly (logged, loop went on) [count]
ROLES = "roles"  # one row per role: role, id, host, pid, state, heartbeat age, frames/s, lag, restarts [rows]

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
