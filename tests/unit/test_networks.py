"""QNetwork and ViewEncoder: shapes, the embedding against a numpy reference, dueling, fusion modes,
mission padding, and publishing weights as numpy arrays."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from higher_dist.config import NetworkConfig
from higher_dist.learning.networks import BagOfWordsEncoder, InstructionEncoder, QNetwork, ViewEncoder, load_weights_numpy, lookup, weights_numpy
from higher_dist.world.spec import DEFAULT_SPEC, VIEW_CHANNEL_VALUES

torch.set_num_threads(1)

SMALL = NetworkConfig(embed_dim=4, conv_channels=(8, 8), frame_stack=2, word_embed_dim=8, text_hidden=8, hidden=16)
VOCAB = DEFAULT_SPEC.vocab_size


def random_views(rng: np.random.Generator, b: int, k: int, v: int = 7) -> np.ndarray:
    """Valid views: attributes only where the kind is an object (key 3, ball 4)."""
    views = np.zeros((b, k, v, v, 4), np.uint8)
    kind = rng.integers(0, 5, (b, k, v, v))
    views[..., 0] = kind
    is_object = kind >= 3
    for ch in (1, 2, 3):
        views[..., ch] = np.where(is_object, rng.integers(1, VIEW_CHANNEL_VALUES[ch], (b, k, v, v)), 0)
    return views


def random_missions(rng: np.random.Generator, b: int, length: int = 10) -> np.ndarray:
    missions = np.zeros((b, length), np.int64)
    for i, n in enumerate(rng.integers(5, 9, b)):
        missions[i, :n] = rng.integers(3, VOCAB, n)
    return missions


def as_tensors(views: np.ndarray, missions: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.from_numpy(views), torch.from_numpy(missions)


@pytest.mark.parametrize("fusion", ["film", "concat"])
@pytest.mark.parametrize("dueling", [True, False])
def test_output_shape_and_both_branches_get_gradients(fusion: str, dueling: bool) -> None:
    torch.manual_seed(0)
    cfg = NetworkConfig(**{**SMALL.__dict__, "fusion": fusion, "dueling": dueling})
    net = QNetwork(cfg)
    rng = np.random.default_rng(0)
    q = net(*as_tensors(random_views(rng, 5, 2), random_missions(rng, 5)))
    assert q.shape == (5, 4) and q.dtype == torch.float32 and torch.isfinite(q).all()
    q.square().sum().backward()
    # Both the view and the instruction branch are trained by the Q loss.
    assert net.view.embed.weight.grad.abs().sum() > 0
    assert net.text.gru.weight_hh_l0.grad.abs().sum() > 0
    assert net.text.embed.weight.grad.abs().sum() > 0


def test_mission_changes_q_values() -> None:
    torch.manual_seed(1)
    net = QNetwork(SMALL)
    rng = np.random.default_rng(1)
    views = random_views(rng, 4, 2)
    q1 = net(*as_tensors(views, random_missions(rng, 4)))
    q2 = net(*as_tensors(views, random_missions(rng, 4)))
    assert not torch.allclose(q1, q2)


def test_dueling_advantage_has_zero_mean() -> None:
    """Q = V + A - mean(A): the mean over actions of Q is exactly the value stream."""
    torch.manual_seed(2)
    net = QNetwork(SMALL)
    captured = {}
    net.value.register_forward_hook(lambda mod, inp, out: captured.__setitem__("v", out))
    net.advantage.register_forward_hook(lambda mod, inp, out: captured.__setitem__("a", out))
    rng = np.random.default_rng(2)
    q = net(*as_tensors(random_views(rng, 6, 2), random_missions(rng, 6)))
    assert torch.allclose(q.mean(dim=1), captured["v"].squeeze(1), atol=1e-6)
    assert torch.allclose(q - q.mean(dim=1, keepdim=True),
                          captured["a"] - captured["a"].mean(dim=1, keepdim=True), atol=1e-6)


def test_extra_padding_and_batch_company_do_not_change_output() -> None:
    """Trailing PADs are ignored, and a sample's Q does not depend on the lengths of its batch mates
    (the GRU state is taken at each mission's own last word)."""
    torch.manual_seed(3)
    net = QNetwork(SMALL).eval()
    rng = np.random.default_rng(3)
    views, missions = random_views(rng, 6, 2), random_missions(rng, 6, length=10)
    q = net(*as_tensors(views, missions))
    padded = np.concatenate([missions, np.zeros((6, 7), np.int64)], axis=1)
    assert torch.allclose(q, net(*as_tensors(views, padded)), atol=1e-6)
    for i in range(6):
        alone = net(*as_tensors(views[i:i + 1], missions[i:i + 1]))
        assert torch.allclose(q[i:i + 1], alone, atol=1e-5)


def test_embedding_matches_numpy_reference() -> None:
    """embed_views sums the 4 channel embeddings of each cell (rows offset per channel) and lays the
    frames side by side along features: (B, k*E, V, V)."""
    torch.manual_seed(4)
    enc = ViewEncoder(embed_dim=3, conv_channels=(4,), in_frames=2)
    rng = np.random.default_rng(4)
    views = random_views(rng, 3, 2)
    table = enc.embed.weight.detach().numpy()
    offsets = np.cumsum((0,) + VIEW_CHANNEL_VALUES[:-1])
    expected = np.zeros((3, 2 * 3, 7, 7), np.float32)
    for b in range(3):
        for f in range(2):
            for y in range(7):
                for x in range(7):
                    cell = sum(table[offsets[c] + views[b, f, y, x, c]] for c in range(4))
                    expected[b, f * 3:(f + 1) * 3, y, x] = cell
    got = enc.embed_views(torch.from_numpy(views))
    assert got.shape == (3, 6, 7, 7)
    np.testing.assert_allclose(got.detach().numpy(), expected, rtol=1e-6, atol=1e-6)


def test_lookup_gradient_matches_autograd_embedding() -> None:
    torch.manual_seed(5)
    table = torch.randn(30, 5, requires_grad=True)
    index = torch.randint(0, 30, (7, 11))
    upstream = torch.randn(7, 11, 5)
    (lookup(index, table) * upstream).sum().backward()
    ours = table.grad.clone()
    table.grad = None
    (F.embedding(index, table) * upstream).sum().backward()
    assert torch.allclose(ours, table.grad, atol=1e-6)


def test_unrolled_gru_matches_torch_gru_in_values_and_gradients() -> None:
    """The compiled loss runs the instruction GRU as `unrolled` (biases inside the gates, no hidden
    product at the first step); it must be torch's GRU, read at each mission's last word."""
    torch.manual_seed(3)
    enc = InstructionEncoder(VOCAB, word_embed_dim=8, hidden=6)
    with torch.no_grad():  # non-zero biases, so folding them into the gates is exercised
        enc.gru.bias_ih_l0.normal_()
        enc.gru.bias_hh_l0.normal_()
    missions = torch.from_numpy(random_missions(np.random.default_rng(4), 9))
    missions[0, 1:] = 0  # a one-word mission: only the first step counts
    lengths = (missions != 0).sum(dim=1)
    words = F.embedding(missions, enc.embed.weight)
    upstream = torch.randn(9, 6)

    def grads(out: torch.Tensor) -> list[torch.Tensor]:
        return list(torch.autograd.grad((out * upstream).sum(), list(enc.gru.parameters())))

    ours = enc.unrolled(words, lengths)
    theirs = enc(missions)  # eager: torch's GRU, gathered at length - 1
    assert torch.allclose(ours, theirs, atol=1e-5)
    for a, b in zip(grads(enc.unrolled(words, lengths)), grads(enc(missions))):
        assert torch.allclose(a, b, atol=1e-5)


def test_bag_of_words_matches_a_numpy_reference_and_ignores_order_and_padding() -> None:
    """network.text=bow: tanh(W sum(word vectors of the real words) + b), the same for any order of the
    words and any padding, and its gradient reaches the word vectors and the layer."""
    torch.manual_seed(5)
    enc = BagOfWordsEncoder(VOCAB, word_embed_dim=8, hidden=6)
    with torch.no_grad():  # a PAD row that is not zero: masking, not the table, must keep PADs out
        enc.embed.weight[0].normal_()
    rng = np.random.default_rng(6)
    missions = random_missions(rng, 7)
    table, w, b = (t.detach().numpy() for t in (enc.embed.weight, enc.out.weight, enc.out.bias))
    expected = np.stack([np.tanh(w @ table[m[m != 0]].sum(axis=0) + b) for m in missions])
    ours = enc(torch.from_numpy(missions))
    np.testing.assert_allclose(ours.detach().numpy(), expected, atol=1e-5)
    # The same words in another order, and padded to a longer row: the same features.
    shuffled = np.zeros((7, 14), np.int64)
    for i, m in enumerate(missions):
        words = m[m != 0]
        shuffled[i, : len(words)] = rng.permutation(words)
    assert torch.allclose(enc(torch.from_numpy(shuffled)), ours, atol=1e-6)
    ours.square().sum().backward()
    assert enc.embed.weight.grad[3:].abs().sum() > 0 and enc.out.weight.grad.abs().sum() > 0
    assert enc.embed.weight.grad[0].abs().sum() == 0  # PAD words take no part


def test_q_network_takes_either_instruction_encoder_and_refuses_another() -> None:
    torch.manual_seed(7)
    rng = np.random.default_rng(8)
    views, missions = as_tensors(random_views(rng, 4, 2), random_missions(rng, 4))
    for text, encoder in (("gru", InstructionEncoder), ("bow", BagOfWordsEncoder)):
        net = QNetwork(NetworkConfig(**{**SMALL.__dict__, "text": text}))
        assert isinstance(net.text, encoder)
        q = net(views, missions)
        assert q.shape == (4, 4) and torch.isfinite(q).all()
    with pytest.raises(ValueError, match="network.text"):
        QNetwork(NetworkConfig(**{**SMALL.__dict__, "text": "lstm"}))


def test_encoder_output_sizes_and_deep_stacks() -> None:
    enc = ViewEncoder(embed_dim=4, conv_channels=(8, 16), in_frames=3)
    assert (enc.out_channels, enc.out_size, enc.out_dim) == (16, 3, 16 * 9)
    # More layers than a 7x7 view can take unpadded: the last ones keep the 1x1 map.
    deep = ViewEncoder(embed_dim=4, conv_channels=(8, 8, 8, 8), in_frames=1)
    out = deep(torch.zeros(2, 1, 7, 7, 4, dtype=torch.uint8))
    assert out.shape == (2, 8, 1, 1) and deep.out_dim == 8


def test_invalid_views_are_refused() -> None:
    enc = ViewEncoder(embed_dim=4, conv_channels=(8,), in_frames=1)
    views = torch.zeros(2, 1, 7, 7, 4, dtype=torch.uint8)
    views[1, 0, 3, 3, 2] = VIEW_CHANNEL_VALUES[2]  # one past the last shade value
    with pytest.raises(ValueError, match="out of range"):
        enc(views)
    with pytest.raises(ValueError, match="out of range"):
        enc(torch.full((1, 1, 7, 7, 4), -1, dtype=torch.int64))
    with pytest.raises(ValueError, match="integer"):
        enc(torch.zeros(1, 1, 7, 7, 4))
    with pytest.raises(ValueError, match="expected"):
        enc(torch.zeros(1, 2, 7, 7, 4, dtype=torch.uint8))  # two frames for a one-frame encoder


def test_weights_numpy_round_trip() -> None:
    torch.manual_seed(6)
    a = QNetwork(SMALL)
    torch.manual_seed(7)
    b = QNetwork(SMALL)
    arrays = weights_numpy(a)
    assert arrays and all(x.dtype == np.float32 for x in arrays.values())
    rng = np.random.default_rng(6)
    inputs = as_tensors(random_views(rng, 3, 2), random_missions(rng, 3))
    assert not torch.allclose(a(*inputs), b(*inputs))
    load_weights_numpy(b, arrays)
    assert torch.equal(a(*inputs), b(*inputs))
    # The arrays are copies: scribbling on them does not touch the network.
    before = a(*inputs)
    for x in arrays.values():
        x[...] = 0
    assert torch.equal(a(*inputs), before)


def test_load_weights_numpy_rejects_mismatch_without_partial_update() -> None:
    torch.manual_seed(8)
    net = QNetwork(SMALL)
    good = weights_numpy(net)
    reference = {k: v.copy() for k, v in good.items()}
    name = "trunk.weight"

    missing = {k: np.ones_like(v) for k, v in good.items() if k != name}
    with pytest.raises(ValueError, match=name):
        load_weights_numpy(net, missing)

    extra = {**good, "bogus.weight": np.zeros(3, np.float32)}
    with pytest.raises(ValueError, match="bogus.weight"):
        load_weights_numpy(net, extra)

    misshapen = {k: np.ones_like(v) for k, v in good.items()}
    misshapen[name] = np.ones((3, 3), np.float32)
    with pytest.raises(ValueError, match=name):
        load_weights_numpy(net, misshapen)

    # Validation happens before any copy: the failed loads left every weight as it was.
    for k, v in weights_numpy(net).items():
        np.testing.assert_array_equal(v, reference[k])

    # A network of another size is refused too.
    other = QNetwork(NetworkConfig(**{**SMALL.__dict__, "hidden": 32}))
    with pytest.raises(ValueError, match="shape"):
        load_weights_numpy(other, good)


def test_views_are_checked_while_another_thread_compiles() -> None:
    """torch.compile raises one process-wide "compiling" flag while the learner's loss compiles in the
    background; eager forwards meanwhile (the learner's, the evaluator's) must still refuse bad views."""
    enc = ViewEncoder(embed_dim=4, conv_channels=(8,), in_frames=1)
    views = torch.zeros(1, 1, 7, 7, 4, dtype=torch.uint8)
    views[0, 0, 3, 3, 0] = 9
    with torch.compiler._compile_session_context():
        assert torch.compiler.is_compiling()
        with pytest.raises(ValueError, match="out of range"):
            enc(views)


def test_every_seed_starts_with_q_near_zero_unlike_the_default_init() -> None:
    # The paper world's Q-network (default config): PyTorch's default init gave seeds an initial Q from
    # -0.25 to +0.7, which a slowly copied target carries for hundreds of thousands of frames.
    rng = np.random.default_rng(0)
    views = torch.from_numpy(random_views(rng, 64, NetworkConfig().frame_stack))
    mission = torch.from_numpy(rng.integers(1, VOCAB, (64, 8)))
    scaled, default = [], []
    for seed in range(8):
        for scale, out in ((NetworkConfig().head_init_scale, scaled), (1.0, default)):
            torch.manual_seed(seed)
            net = QNetwork(NetworkConfig(head_init_scale=scale))
            with torch.no_grad():
                out.append(float(net(views, mission).abs().max()))
    assert max(scaled) < 0.02, scaled
    assert max(default) > 0.1, default  # what the scaling prevents


# -- BabyAI 1.1's network options (network.film_blocks) on both world families --------------------------

def babyai_like_spec():
    """A BabyAI level's encodings (7 actions, minigrid's channel values, its vocabulary) without minigrid."""
    from higher_dist.world import babyai_language
    from higher_dist.world.spec import BABYAI_ACTION_NAMES, BABYAI_CHANNEL_VALUES, WorldSpec

    return WorldSpec(view_size=7, max_steps=64, mission_len=babyai_language.MISSION_LEN,
                     vocab_size=len(babyai_language.VOCAB), n_actions=len(BABYAI_ACTION_NAMES),
                     channel_values=BABYAI_CHANNEL_VALUES, family="babyai")


def spec_views(rng: np.random.Generator, spec, b: int, k: int) -> torch.Tensor:
    values = np.array(spec.channel_values)
    return torch.from_numpy((rng.random((b, k, spec.view_size, spec.view_size, 4)) * values).astype(np.uint8))


def spec_missions(rng: np.random.Generator, spec, b: int) -> torch.Tensor:
    missions = np.zeros((b, spec.mission_len), np.int64)
    for i, n in enumerate(rng.integers(3, spec.mission_len + 1, b)):
        missions[i, :n] = rng.integers(3, spec.vocab_size, n)
    return torch.from_numpy(missions)


OPTIONS = [("film", 0), ("film", 1), ("film", 2), ("concat", 0)]


@pytest.mark.parametrize("family", ["fetchattr", "babyai"])
@pytest.mark.parametrize("fusion,film_blocks", OPTIONS)
@pytest.mark.parametrize("dueling", [True, False])
def test_every_network_option_has_the_spec_shapes_and_trains_every_layer(family, fusion, film_blocks, dueling):
    spec = DEFAULT_SPEC if family == "fetchattr" else babyai_like_spec()
    cfg = NetworkConfig(**{**SMALL.__dict__, "fusion": fusion, "film_blocks": film_blocks, "dueling": dueling})
    torch.manual_seed(3)
    net = QNetwork(cfg, spec)
    rng = np.random.default_rng(3)
    q = net(spec_views(rng, spec, 6, cfg.frame_stack), spec_missions(rng, spec, 6))
    assert q.shape == (6, spec.n_actions) and torch.isfinite(q).all()
    assert len(net.view.film_blocks) == film_blocks
    q.square().sum().backward()
    layers = [net.view.embed, *net.view.convs, *net.view.film_blocks, net.text.embed, net.trunk]
    layers += [net.film] if fusion == "film" else []
    for layer in layers:
        assert layer.weight.grad is not None and layer.weight.grad.abs().sum() > 0, layer
    assert net.text.gru.weight_hh_l0.grad.abs().sum() > 0


def test_residual_film_blocks_are_the_identity_when_their_branch_is_zero():
    """h + relu(FiLM(conv(h))): with the block's conv and the FiLM layer zeroed (gamma 1, beta 0) the
    blocks pass the stem's maps through unchanged; a non-zero branch changes them."""
    torch.manual_seed(4)
    plain = QNetwork(NetworkConfig(**{**SMALL.__dict__, "film_blocks": 0}))
    blocks = QNetwork(NetworkConfig(**{**SMALL.__dict__, "film_blocks": 2}))
    blocks.view.convs.load_state_dict(plain.view.convs.state_dict())
    blocks.view.embed.load_state_dict(plain.view.embed.state_dict())
    c = plain.view.out_channels
    with torch.no_grad():
        for conv in blocks.view.film_blocks:
            conv.weight.zero_()
            conv.bias.zero_()
    rng = np.random.default_rng(4)
    views = torch.from_numpy(random_views(rng, 5, SMALL.frame_stack))
    identity = (torch.ones(5, c), torch.zeros(5, c))
    expected = plain.view(views, film=identity)
    got = blocks.view(views, film=(torch.ones(5, 2 * c), torch.zeros(5, 2 * c)))
    assert torch.equal(got, expected)
    # Zero modulation but a live convolution: the branch adds relu(conv(h)) >= 0, somewhere > 0.
    with torch.no_grad():
        blocks.view.film_blocks[0].bias.fill_(0.5)
    changed = blocks.view(views, film=(torch.ones(5, 2 * c), torch.zeros(5, 2 * c)))
    assert (changed >= expected).all() and (changed > expected).any()


def test_bad_film_blocks_are_refused_naming_the_field():
    from higher_dist.config import ConfigError, override, validate
    from higher_dist.config_presets import make_config

    with pytest.raises(ValueError, match="film_blocks.*fusion 'film'"):
        QNetwork(NetworkConfig(**{**SMALL.__dict__, "fusion": "concat", "film_blocks": 1}))
    with pytest.raises(ValueError, match="film_blocks: must be an integer >= 0"):
        ViewEncoder(4, (8,), 1, film_blocks=-1)
    cfg = make_config("higher", "small")
    with pytest.raises(ConfigError, match="network.film_blocks: must be >= 0"):
        validate(override(cfg, **{"network.film_blocks": -1}))
    with pytest.raises(ConfigError, match="network.film_blocks: 1 block.*network.fusion=film"):
        validate(override(cfg, **{"network.film_blocks": 1, "network.fusion": "concat"}))
