"""The generated references: docs/configuration.md and docs/metrics.md match what config.py and metrics.py
say now, and every field and key has its meaning written next to it."""
from higher_dist import docs_gen
from higher_dist.config import Config


def test_the_committed_references_are_what_the_code_generates():
    for path, text in docs_gen.outputs().items():
        assert path.read_text() == text, f"{path.name} is out of date: run `make docs`"


def test_every_config_field_has_a_meaning_and_a_row_under_its_set_path():
    comments = docs_gen._field_comments()
    leaves = list(docs_gen._leaves(Config()))
    missing = [path for path, owner, f in leaves if not comments.get((owner, f.name))]
    assert not missing, f"give these fields a one-line comment in config.py: {missing}"
    table = docs_gen.configuration_md()
    assert all(f"| `{path}` |" in table for path, _, _ in leaves) and "| `dqn.lr` | float | `0.0005` |" in table


def test_every_metric_key_has_a_meaning_and_the_presets_differences_are_named():
    entries = list(docs_gen._metric_entries())
    assert not [key for _, key, meaning, _ in entries if not meaning]
    assert ("success", "success_rate_eval_train", "greedy success on training goals, latest evaluation",
            "fraction") in entries
    assert any(key == "replay_*" for _, key, _, _ in entries)
    table = docs_gen.configuration_md()
    assert ("| `relabel.strategy` | str: none \\| expert \\| noisy \\| learned | `none` | "
            "expert (her); noisy (noisy-her); learned (higher) |") in table


def test_every_key_the_learner_records_is_in_the_metrics_reference():
    from higher_dist import metrics as m
    from higher_dist.config_presets import make_config
    from higher_dist.learning.learner import Learner
    from higher_dist.learning.random_episodes import real_episodes
    from higher_dist.roles.registry import RoleRegistry

    cfg = make_config("her", "small", **{"replay.min_size": 50})
    core = Learner(cfg)
    core.add_episodes(real_episodes(cfg.world, 12, seed=1, relabelled=True))
    core.train_available(max_updates=2)
    record = {**core.metrics(), **RoleRegistry().telemetry({"role": "learner"}, 0, {}), **dict.fromkeys(m.RELABEL_KEYS)}
    documented = [key for _, key, _, _ in docs_gen._metric_entries()]

    def covered(key: str) -> bool:
        return any(key == d or (d.endswith("*") and key.startswith(d[:-1]))
                   or (d.startswith("*") and key.endswith(d[1:])) for d in documented)

    assert core.updates > 0 and m.LOSS in record
    assert not [key for key in record if not covered(key)]


def test_the_configuration_reference_names_what_a_babyai_level_changes():
    from higher_dist.config_presets import make_config

    table = docs_gen.configuration_md()
    level, ours = make_config("higher", "BabyAI-PickupDist-v0"), make_config("higher", "paper")
    changed = [path for path, _, _ in docs_gen._leaves(level)
               if docs_gen._get(level, path) != docs_gen._get(ours, path)]
    assert "frames" in changed and "generator.batch_size" in changed
    rows = {line.split("`")[1]: line for line in table.splitlines() if line.startswith("| `")}
    # Named either way: what the level sets, or what only the paper world sets (the level keeping the default).
    assert not [path for path in changed if "BabyAI level" not in rows[path] and "paper world" not in rows[path]]
    assert "paper world" in rows["network.text"]
