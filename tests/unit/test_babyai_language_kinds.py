"""The BabyAI language of each level kind (pick up, go to, open): its grammar round trip, what it refuses,
every mission the levels say, the fixed vocabulary's ids, and which levels are supported."""
from __future__ import annotations

import numpy as np
import pytest

from higher_dist.config_presets import make_config
from higher_dist.world import babyai_language as lang
from higher_dist.world.babyai import BatchedBabyAI, level_facts, supported_levels
from higher_dist.world.spec import WorldSpec

KINDS = ("pickup", "goto", "open")
# (colours or none) x (types or "object") x (locations or none) x (the, a)
N_SENTENCES = {"pickup": 7 * 4 * 5 * 2, "goto": 7 * 5 * 5 * 2, "open": 7 * 1 * 5 * 2}
# The vocabulary as checkpoints made before the go-to and open levels know it: its ids must not move.
OLD_VOCAB = ("<pad>", "<beg>", "<end>", "pick", "up", "the", "a", "red", "green", "blue", "purple", "yellow",
             "grey", "key", "ball", "box", "object", "on", "your", "left", "right", "in", "front", "of", "you",
             "behind")


def sentences(kind: str) -> list[str]:
    language = lang.LANGUAGES[kind]
    return [language.decode(t) for t in language.mission_tokens(language.all_attrs())]


@pytest.mark.parametrize("kind", KINDS)
def test_round_trip_for_every_sentence_of_each_kind(kind):
    language = lang.LANGUAGES[kind]
    assert language.kind == kind and repr(language) == f"BabyAILanguage({kind!r})"
    attrs = language.all_attrs()
    assert len(attrs) == N_SENTENCES[kind] == len({tuple(a) for a in attrs.tolist()})
    tokens = language.mission_tokens(attrs)
    assert tokens.shape == (len(attrs), lang.MISSION_LEN) and tokens.dtype == np.int64
    texts = set()
    for row, t, marked in zip(attrs, tokens, lang.with_markers(tokens)):
        text = language.decode(t)
        texts.add(text)
        assert text.startswith(" ".join(language.verb) + " ")
        assert (language.encode(text) == t).all() and language.describe(row) == text
        for form in (t, text, marked):
            parsed = language.parse(form)
            assert parsed is not None and parsed.dtype == np.int8 and (parsed == row).all(), (text, parsed)
    assert len(texts) == len(attrs)
    parsed, ok = language.parse_many(tokens)
    assert ok.all() and (parsed == attrs).all()


def test_each_kind_names_only_its_types():
    goto, open_, pickup = (lang.LANGUAGES[k] for k in ("goto", "open", "pickup"))
    assert {lang.TYPES[t] for t in pickup.types} == {"key", "ball", "box"}
    assert {lang.TYPES[t] for t in goto.types} == {"key", "ball", "box", "door"}
    assert {lang.TYPES[t] for t in open_.types} == {"door"}
    assert (open_.all_attrs()[:, 1] == lang.DOOR).all()  # "open" always names a door
    assert "go to the door" in sentences("goto") and "go to a red object on your left" in sentences("goto")
    assert "open the grey door behind you" in sentences("open") and "open a door" in sentences("open")
    assert "pick up a blue box in front of you" in sentences("pickup")
    # The module-level functions are the pickup language's.
    assert (lang.all_attrs() == pickup.all_attrs()).all() and lang.parse("go to the red ball") is None


@pytest.mark.parametrize("kind", KINDS)
def test_another_kinds_sentences_do_not_parse(kind):
    language = lang.LANGUAGES[kind]
    for other in KINDS:
        if other != kind:
            refused = [text for text in sentences(other) if language.parse(text) is not None]
            assert refused == [], (kind, other, refused[:3])
            tokens = lang.LANGUAGES[other].mission_tokens(lang.LANGUAGES[other].all_attrs())
            assert not language.parse_many(tokens)[1].any()


@pytest.mark.parametrize("kind, text", [
    ("open", "open the red ball"), ("open", "open the key"), ("open", "open a object"), ("open", "open the red object"),
    ("pickup", "pick up the door"), ("pickup", "pick up a red door on your left"),
    ("goto", "go the red ball"), ("goto", "to the red ball"), ("goto", "go to red ball"), ("goto", "go to the"),
    ("goto", "go to the door door"), ("goto", "go to the ball on your"), ("open", "open door"),
    ("open", "open the door in front of"), ("open", "open open the door"), ("goto", "go to the door please"),
    ("goto", "open the door"), ("open", "go to the door"), ("pickup", "go to the key")])
def test_ungrammatical_or_wrong_kind_sentences_do_not_parse(kind, text):
    language = lang.LANGUAGES[kind]
    assert language.parse(text) is None
    known = all(w in lang.WORD_TO_ID for w in text.split())
    if known:  # as word ids too
        assert language.parse(lang.encode(text)) is None


@pytest.mark.parametrize("kind", KINDS)
def test_expert_names_colour_and_type_with_the_article(kind):
    language = lang.LANGUAGES[kind]
    type_ = lang.DOOR if kind == "open" else lang.TYPES.index("ball")
    red = lang.COLORS.index("red")
    achieved = np.array([[red, type_, 0, 0], [red, type_, 13, 1], [red, type_, 0, 1]], dtype=np.int8)
    verb, name = " ".join(language.verb), lang.TYPES[type_]
    texts = [language.decode(t) for t in language.expert_tokens(achieved)]
    # The third column of an achieved outcome is a location mask, never named by the expert.
    assert texts == [f"{verb} the red {name}", f"{verb} a red {name}", f"{verb} a red {name}"]


@pytest.mark.parametrize("level", ["BabyAI-GoToLocal-v0", "BabyAI-OpenDoor-v0", "BabyAI-OpenDoorLoc-v0",
                                   "BabyAI-PickupLoc-v0"])
def test_every_mission_of_a_level_parses_to_its_goal(level):
    """50 first resets: the world's mission is minigrid's text, and its goal is what the level's own
    `ObjDesc` describes (colour, type, location, several matching objects: "a")."""
    batch = 50
    world = BatchedBabyAI(level, batch, env_seeds=list(range(batch)))
    _, missions = world.reset()
    spec = WorldSpec.of(make_config("her", level).world)
    language = spec.language
    assert language is lang.LANGUAGES[level_facts(level).kind] and spec.level_kind == language.kind
    forms = set()
    for env, mission, goal in zip(world.envs, missions, world.goal):
        desc = env.instrs.desc
        expected = [lang.COLORS.index(desc.color) if desc.color else -1,
                    lang.TYPES.index(desc.type) if desc.type else -1,
                    lang.LOCS.index(desc.loc) if desc.loc else -1, int(len(desc.obj_set) > 1)]
        assert language.decode(mission) == env.mission
        assert goal.tolist() == expected and language.parse(mission).tolist() == expected, env.mission
        assert language.parse(env.mission).tolist() == expected
        forms.add((desc.loc is not None, expected[3]))
    # The seeds cover both articles, and on the levels that name a location only sometimes, both forms.
    assert {plural for _, plural in forms} == {0, 1}, forms
    if level in ("BabyAI-OpenDoor-v0", "BabyAI-PickupLoc-v0"):
        assert {loc for loc, _ in forms} == {False, True}, forms


def test_vocabulary_keeps_the_ids_of_checkpoints():
    assert lang.VOCAB[: len(OLD_VOCAB)] == OLD_VOCAB and len(OLD_VOCAB) == 26
    assert lang.VOCAB[len(OLD_VOCAB):] == ("go", "to", "open", "door")
    assert len(set(lang.VOCAB)) == len(lang.VOCAB)
    assert all(lang.WORD_TO_ID[w] == i for i, w in enumerate(lang.VOCAB))
    for kind in KINDS:
        assert WorldSpec.of(make_config("her", {"pickup": "BabyAI-PickupLoc-v0", "goto": "BabyAI-GoToLocal-v0",
                                                "open": "BabyAI-OpenDoor-v0"}[kind]).world).language.VOCAB == lang.VOCAB


def test_supported_levels_per_kind():
    goto, open_, pickup = supported_levels("goto"), supported_levels("open"), supported_levels("pickup")
    assert {"BabyAI-GoToLocal-v0", "BabyAI-GoToObj-v0", "BabyAI-GoToRedBall-v0"} <= set(goto)
    assert {"BabyAI-OpenDoor-v0", "BabyAI-OpenDoorLoc-v0"} <= set(open_)
    assert {"BabyAI-PickupDist-v0", "BabyAI-PickupLoc-v0"} <= set(pickup)
    assert not (set(goto) & set(open_)) and not (set(goto) & set(pickup)) and not (set(open_) & set(pickup))
    assert set(supported_levels()) == set(goto) | set(open_) | set(pickup)
    for level in goto + open_:
        assert level_facts(level).kind == ("goto" if level in goto else "open")


@pytest.mark.parametrize("level", ["BabyAI-GoToSeq-v0", "BabyAI-PutNextLocal-v0", "BabyAI-OpenDoorDebug-v0",
                                   "BabyAI-PickupDistDebug-v0", "BabyAI-ActionObjDoor-v0", "BabyAI-BossLevel-v0"])
def test_unsupported_levels_are_refused_in_one_line(level):
    assert level not in supported_levels()
    for make in (level_facts, lambda name: BatchedBabyAI(name, 1)):
        with pytest.raises(ValueError) as error:
            make(level)
        message = str(error.value)
        assert "\n" not in message and level in message and "supported are" in message, message
