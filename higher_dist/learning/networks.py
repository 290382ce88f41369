"""The Q-network: a view encoder, an instruction encoder and their fusion, over 4 actions.

Inputs follow docs/architecture.md: a stack of k egocentric views `(B, k, 7, 7, 4)` uint8 with channels
[kind, color, shade, size] and a PAD-padded mission `(B, L)` of word ids (PAD=0, words first).

Sizes are kept lean on purpose: the learner must run thousands of samples per second on one CPU
thread (measure with `higher-bench learner`, which takes `--net FIELD=VALUE` overrides), and a 7x7
view with a 6-8 word mission needs little capacity. On a supervised probe (say where the described
object lies in the view) embed 8 / convs (16, 32) / GRU 32 / hidden 64 scored within noise of a
network four times its size, and FiLM beat concatenation.
"""
from __future__ import annotations

import threading
from contextlib import contextmanager

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from higher_dist.config import FUSIONS, TEXT_ENCODERS, NetworkConfig
from higher_dist.world.language import PAD as PAD_ID
from higher_dist.world.spec import DEFAULT_SPEC, WorldSpec


_trace_state = threading.local()


@torch.compiler.assume_constant_result
def on_traced_path() -> bool:
    """True while `traced_path` is on in this thread and torch.compile is tracing: the learner's
    compiled loss then takes the graph-friendly forms below (no data-dependent branches or raises;
    same maths). torch.compiler.is_compiling() alone is not enough: it is one flag for the whole
    process while any thread compiles, and the learner keeps stepping eagerly (and the evaluator
    thread acting) while its loss compiles in the background."""
    return bool(getattr(_trace_state, "on", False)) and torch.compiler.is_compiling()


@contextmanager
def traced_path():
    """Mark this thread's calls as the compiled loss's (set by learning.compiled_loss)."""
    before = getattr(_trace_state, "on", False)
    _trace_state.on = True
    try:
        yield
    finally:
        _trace_state.on = before


class _SmallTableLookup(torch.autograd.Function):
    """`F.embedding(index, table)` with a cheaper backward for a small table and many lookups.

    The stock dense embedding backward sorts all indices; accumulating the gradient rows with
    `index_add_` measured ~2.5x faster on one CPU thread for the view's B*k*49 cell lookups.
    """

    @staticmethod
    def forward(ctx, index: torch.Tensor, table: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        ctx.save_for_backward(index)
        ctx.rows = table.shape[0]
        return F.embedding(index, table)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        (index,) = ctx.saved_tensors
        grad = grad.reshape(-1, grad.shape[-1])
        grad_table = grad.new_zeros(ctx.rows, grad.shape[1]).index_add_(0, index.reshape(-1), grad)
        return None, grad_table


def lookup(index: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    """Rows of `table` named by `index` (any shape) -> index.shape + (E,)."""
    if torch.is_grad_enabled() and table.requires_grad and not on_traced_path():
        return _SmallTableLookup.apply(index, table)
    return F.embedding(index, table)


class ViewEncoder(nn.Module):
    """Embeds a frame stack of views and runs 3x3 convolutions over it.

    Each cell's 4 channel values are embedded, one table with per-channel row offsets, and summed (an
    additive code of the object's attributes); this is BabyAI 1.1's bag-of-words cell embedding (Hui
    et al. 2020: one learned vector per (channel, value) pair, summed over channels). The k frames are
    concatenated along features, so the first convolution sees motion and remembered objects.
    Convolutions are unpadded ("valid") while the map is at least 3 cells wide: on a 7x7 view that is
    cheaper than padding and still covers every cell. Nothing max-pools: BabyAI 1.1's other encoder
    option (no pooling in the first layers) is what this encoder always does.

    film_blocks > 0 adds BabyAI 1.1's residual FiLM blocks after the convolutions, each
    h <- h + relu(FiLM(conv3x3(h))) with a padded convolution that keeps channels and map size; with
    0, FiLM modulates the last convolution. Reused by the instruction generator (with `in_frames=1`).
    """

    def __init__(self, embed_dim: int, conv_channels: tuple[int, ...], in_frames: int,
                 spec: WorldSpec = DEFAULT_SPEC, film_blocks: int = 0):
        super().__init__()
        if not conv_channels:
            raise ValueError("conv_channels: needs at least one layer")
        if isinstance(film_blocks, bool) or not isinstance(film_blocks, int) or film_blocks < 0:
            raise ValueError(f"film_blocks: must be an integer >= 0, got {film_blocks!r}")
        self.embed_dim = embed_dim
        self.in_frames = in_frames
        self.view_size = view_size = spec.view_size
        self.channel_values = tuple(spec.channel_values)
        # A cell's channel values read as one mixed-radix number: its index among all possible cells
        # (5*7*6*6 = 1260 on the global tables).
        self.cell_codes = int(np.prod(self.channel_values))
        self.cell_radix = tuple(int(np.prod(self.channel_values[i + 1:])) for i in range(len(self.channel_values)))
        # Rows: kind values, then color, shade and size values (offsets 0, 5, 12, 18).
        self.embed = nn.Embedding(sum(self.channel_values), embed_dim)
        # Not persistent: a constant of the encoding, not a weight to publish or checkpoint.
        self.register_buffer("channel_max", torch.tensor(spec.channel_max, dtype=torch.uint8), persistent=False)
        # Not persistent either: the first row of each channel's values in `embed`.
        offsets = np.concatenate([[0], np.cumsum(self.channel_values)[:-1]])
        self.register_buffer("channel_offsets", torch.as_tensor(offsets, dtype=torch.long), persistent=False)
        convs = []
        in_ch, size = in_frames * embed_dim, view_size
        for out_ch in conv_channels:
            pad = 0 if size >= 3 else 1
            convs.append(nn.Conv2d(in_ch, out_ch, kernel_size=3, padding=pad))
            size = size - 2 + 2 * pad
            in_ch = out_ch
        self.convs = nn.ModuleList(convs)
        # Padded: the skip connection adds the block's input to its output, cell by cell.
        self.film_blocks = nn.ModuleList(nn.Conv2d(in_ch, in_ch, kernel_size=3, padding=1) for _ in range(film_blocks))
        self.film_layers = max(1, film_blocks)  # layers a FiLM (gamma, beta) pair is wanted for
        self.out_channels = in_ch
        self.out_size = size  # spatial side of the last feature map
        self.out_dim = in_ch * size * size

    def cell_table(self) -> torch.Tensor:
        """(1260, E): the summed embedding of every possible cell, from the 24-row channel table.

        Summing the 4 rows once per table entry (10k floats) instead of once per cell of the batch
        (B*k*49 cells) makes the per-cell work a single lookup."""
        rows = torch.split(self.embed.weight, self.channel_values)
        kind, color, shade, size = rows
        table = (kind[:, None, None, None] + color[None, :, None, None]
                 + shade[None, None, :, None] + size[None, None, None, :])
        return table.reshape(self.cell_codes, self.embed_dim)

    def channel_embeddings(self, cells: torch.Tensor) -> torch.Tensor:
        """(B, channels) integer cells -> (B, channels * E): each channel's own row of the table, side by
        side rather than summed (the generator's front-cell shortcut)."""
        return F.embedding(cells.long() + self.channel_offsets, self.embed.weight).flatten(1)

    def check_views(self, views: torch.Tensor) -> None:
        """ValueError unless `views` is (B, k, V, V, 4) of integers within each channel's range."""
        if views.ndim != 5 or views.shape[1] != self.in_frames or views.shape[4] != len(self.channel_values):
            raise ValueError(f"views: expected (B, {self.in_frames}, V, V, 4), got {tuple(views.shape)}")
        if views.dtype.is_floating_point or views.dtype.is_complex or views.dtype == torch.bool:
            raise ValueError(f"views: expected an integer dtype (uint8), got {views.dtype}")
        # An out-of-range value would silently alias another cell's code: refuse it (cheap: one
        # reduction over uint8).
        too_big = (views.amax(dim=(0, 1, 2, 3)) > self.channel_max).any()
        if bool(too_big) or (views.dtype != torch.uint8 and bool(views.amin() < 0)):
            raise ValueError(f"views: channel values out of range [0, {self.channel_max.tolist()}]")

    def embed_views(self, views: torch.Tensor) -> torch.Tensor:
        """(B, k, V, V, 4) integer views -> (B, k*E, V, V) float maps (channels-last in memory)."""
        b, k, v, _, c = views.shape
        if not on_traced_path():
            # A compiled caller checks before entering the graph (a data-dependent raise would break it).
            self.check_views(views)
        # Frames next to the embedding in memory: the lookup then writes (B, V, V, k*E) directly,
        # which the convolution takes as channels-last without a transposing copy.
        cells = views.permute(0, 2, 3, 1, 4).long()
        radix = self.cell_radix
        code = cells[..., 0] * radix[0] + cells[..., 1] * radix[1] + cells[..., 2] * radix[2] + cells[..., 3]
        x = lookup(code, self.cell_table())
        return x.reshape(b, v, v, k * self.embed_dim).permute(0, 3, 1, 2)

    def forward(self, views: torch.Tensor, film: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """Last feature maps (B, C, S, S), after ReLU. `film=(gamma, beta)`, each (B, film_layers * C),
        modulates the last convolution (or each residual block's) before its ReLU, so the instruction
        can switch feature detectors on or off."""
        h = self.embed_views(views)
        blocks = len(self.film_blocks)
        modulations = None
        if film is not None:
            modulations = list(zip(film[0].chunk(self.film_layers, dim=1), film[1].chunk(self.film_layers, dim=1)))
        last = len(self.convs) - 1
        for i, conv in enumerate(self.convs):
            h = conv(h)
            if i == last and modulations is not None and not blocks:
                h = _film(h, *modulations[0])
            h = F.relu(h)
        for j, conv in enumerate(self.film_blocks):
            branch = conv(h)
            if modulations is not None:
                branch = _film(branch, *modulations[j])
            h = h + F.relu(branch)
        return h


def _film(h: torch.Tensor, gamma: torch.Tensor, beta: torch.Tensor) -> torch.Tensor:
    """Per-channel affine map of (B, C, S, S) maps by (B, C) gamma and beta."""
    return h * gamma[:, :, None, None] + beta[:, :, None, None]


class InstructionEncoder(nn.Module):
    """Word embedding + GRU; returns the hidden state after each mission's last real word.

    The GRU runs over the padded batch, cut to its longest mission, and the state at index length-1
    is gathered. On one CPU thread this measured 10-13% faster for forward+backward than
    pack_padded_sequence (which sorts, runs shrinking per-step batches and unsorts) at L=10,
    B=64..256, and the same without gradients; trailing PADs cannot change the result because they
    come after the gathered step.
    """

    def __init__(self, vocab_size: int, word_embed_dim: int, hidden: int):
        super().__init__()
        self.hidden = hidden
        self.embed = nn.Embedding(vocab_size, word_embed_dim, padding_idx=PAD_ID)
        self.gru = nn.GRU(word_embed_dim, hidden, batch_first=True)

    def forward(self, mission: torch.Tensor) -> torch.Tensor:
        lengths = (mission != PAD_ID).sum(dim=1).clamp(min=1)
        if on_traced_path():
            # Traced: no data-dependent cut, and the recurrence written out so the compiler fuses it.
            return self.unrolled(lookup(mission, self.embed.weight), lengths)
        longest = int(lengths.max())
        if longest < mission.shape[1]:
            mission = mission[:, :longest]  # columns of PAD only: skip their GRU steps
        # PAD rows get no gradient anyway: trailing PADs are cut or come after the gathered step.
        out, _ = self.gru(lookup(mission, self.embed.weight))  # (B, L, H)
        index = (lengths - 1).view(-1, 1, 1).expand(-1, 1, self.hidden)
        return out.gather(1, index).squeeze(1)

    def unrolled(self, words: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """The same GRU as `self.gru` (same weights, same gate equations, r/z/n order) as a loop of
        plain tensor ops over the L steps; each row's state stops changing after its last word, so the
        final state is the one `forward` gathers. Input projections for all steps are one matmul.

        The biases are added inside the gate expressions rather than by the matrix products, and the
        first step skips the hidden product (the state starts at zero): a product with a bias is an
        extern call plus a copy of the broadcast bias, while a sum inside the gates fuses into the
        compiled step's one loop."""
        g = self.gru
        gi = torch.matmul(words, g.weight_ih_l0.t())  # (B, L, 3H), no bias
        b_ir, b_iz, b_in = g.bias_ih_l0.chunk(3)
        b_hr, b_hz, b_hn = g.bias_hh_l0.chunk(3)
        b_r, b_z = b_ir + b_hr, b_iz + b_hz
        h = words.new_zeros(words.shape[0], self.hidden)
        for t in range(words.shape[1]):
            i_r, i_z, i_n = gi[:, t].chunk(3, dim=1)
            if t == 0:
                r = torch.sigmoid(i_r + b_r)
                z = torch.sigmoid(i_z + b_z)
                n = torch.tanh(i_n + b_in + r * b_hn)
            else:
                h_r, h_z, h_n = torch.mm(h, g.weight_hh_l0.t()).chunk(3, dim=1)
                r = torch.sigmoid(i_r + h_r + b_r)
                z = torch.sigmoid(i_z + h_z + b_z)
                n = torch.tanh(i_n + b_in + r * (h_n + b_hn))
            step = n + z * (h - n)
            h = torch.where((t < lengths).unsqueeze(1), step, h)
        return h


WORD_INIT_SCALE = 0.1  # the bag of words' word vectors start at this standard deviation


class BagOfWordsEncoder(nn.Module):
    """Word vectors summed over a mission's real words, then one tanh layer: blind to word order.

    On FetchAttr every word names one attribute value (prefixes name nothing), so order carries nothing
    and every phrasing of one object is the same bag but for its prefix words; the sum is one gather and
    one small product where the GRU runs a step per word. PAD words are masked out, so a mission's
    features do not depend on its padding."""

    def __init__(self, vocab_size: int, word_embed_dim: int, hidden: int):
        super().__init__()
        self.embed = nn.Embedding(vocab_size, word_embed_dim, padding_idx=PAD_ID)
        self.out = nn.Linear(word_embed_dim, hidden)
        with torch.no_grad():  # a sum of ~8 unit-variance vectors would saturate the tanh from the start
            self.embed.weight.mul_(WORD_INIT_SCALE)

    def forward(self, mission: torch.Tensor) -> torch.Tensor:
        real = (mission != PAD_ID).unsqueeze(-1).to(self.embed.weight.dtype)
        bag = (lookup(mission, self.embed.weight) * real).sum(dim=1)
        return torch.tanh(self.out(bag))


def instruction_encoder(cfg: NetworkConfig, vocab_size: int) -> nn.Module:
    """The instruction encoder `cfg.text` names."""
    if cfg.text == "bow":
        return BagOfWordsEncoder(vocab_size, cfg.word_embed_dim, cfg.text_hidden)
    if cfg.text == "gru":
        return InstructionEncoder(vocab_size, cfg.word_embed_dim, cfg.text_hidden)
    raise ValueError(f"network.text: must be one of {', '.join(TEXT_ENCODERS)}, got {cfg.text!r}")


class QNetwork(nn.Module):
    """Q(view stack, mission) over the 4 actions.

    fusion "film": the instruction yields per-channel (gamma, beta) for the last conv maps, or for each
    residual FiLM block's (cfg.film_blocks) (gamma is parametrised as 1 + delta so that it is centred
    on the identity and no channel starts switched off).
    fusion "concat": the flattened view features and the instruction state are concatenated.
    The head is one hidden layer, then a dueling split (value + advantage - mean advantage) or a
    plain linear layer.
    """

    def __init__(self, cfg: NetworkConfig, spec: WorldSpec = DEFAULT_SPEC):
        super().__init__()
        n_actions = spec.n_actions
        if cfg.fusion not in FUSIONS:
            raise ValueError(f"fusion: must be one of {', '.join(FUSIONS)}, got {cfg.fusion!r}")
        self.cfg = cfg
        self.n_actions = n_actions
        self.fusion = cfg.fusion
        self.dueling = cfg.dueling
        if cfg.film_blocks and self.fusion != "film":
            raise ValueError(f"film_blocks: {cfg.film_blocks} block(s) need fusion 'film', got {cfg.fusion!r}")
        self.view = ViewEncoder(cfg.embed_dim, tuple(cfg.conv_channels), cfg.frame_stack, spec, cfg.film_blocks)
        self.text = instruction_encoder(cfg, spec.vocab_size)
        if self.fusion == "film":
            self.film = nn.Linear(cfg.text_hidden, 2 * self.view.film_layers * self.view.out_channels)
            head_in = self.view.out_dim
        else:
            head_in = self.view.out_dim + cfg.text_hidden
        self.trunk = nn.Linear(head_in, cfg.hidden)
        if self.dueling:
            self.value = nn.Linear(cfg.hidden, 1)
            self.advantage = nn.Linear(cfg.hidden, n_actions)
        else:
            self.q = nn.Linear(cfg.hidden, n_actions)
        with torch.no_grad():  # Q ~ 0 at the start whatever the seed (NetworkConfig.head_init_scale)
            for out in (self.value, self.advantage) if self.dueling else (self.q,):
                out.weight.mul_(cfg.head_init_scale)
                out.bias.zero_()

    def forward(self, views: torch.Tensor, mission: torch.Tensor) -> torch.Tensor:
        return self.q_values(views, self.encode_mission(mission))

    def encode_mission(self, mission: torch.Tensor) -> torch.Tensor:
        """(B, L) word ids -> (B, text_hidden) instruction features."""
        return self.text(mission)

    def q_values(self, views: torch.Tensor, text: torch.Tensor) -> torch.Tensor:
        """Q-values from views and precomputed `encode_mission` features: obs and next_obs of a
        transition share one mission, so the loss encodes it once per network."""
        return self.head(self.hidden_features(views, text))

    def hidden_features(self, views: torch.Tensor, text: torch.Tensor) -> torch.Tensor:
        """(B, hidden) features of views fused with the instruction, before the Q head."""
        if self.fusion == "film":
            delta_gamma, beta = self.film(text).chunk(2, dim=1)
            features = self.view(views, film=(1.0 + delta_gamma, beta)).flatten(1)
        else:
            features = torch.cat([self.view(views).flatten(1), text], dim=1)
        return F.relu(self.trunk(features))

    def head(self, h: torch.Tensor) -> torch.Tensor:
        """Q-values (..., n_actions) from hidden features (..., hidden): dueling or plain."""
        if not self.dueling:
            return self.q(h)
        advantage = self.advantage(h)
        return self.value(h) + advantage - advantage.mean(dim=-1, keepdim=True)


def weights_numpy(net: nn.Module) -> dict[str, np.ndarray]:
    """The network's weights as float32 CPU numpy arrays (copies), keyed by state_dict name."""
    return {name: t.detach().to("cpu", torch.float32).numpy().copy() for name, t in net.state_dict().items()}


def load_weights_numpy(net: nn.Module, weights: dict[str, np.ndarray]) -> None:
    """Load `weights_numpy` output into `net`; ValueError names any missing, unexpected or misshapen entry.

    Checked before anything is copied, so a bad message never leaves the network half-updated.
    """
    state = net.state_dict()
    missing = sorted(set(state) - set(weights))
    unexpected = sorted(set(weights) - set(state))
    if missing or unexpected:
        raise ValueError(f"weights: missing {missing}, unexpected {unexpected}")
    for name, tensor in state.items():
        shape = tuple(np.shape(weights[name]))
        if shape != tuple(tensor.shape):
            raise ValueError(f"weights: {name} has shape {shape}, expected {tuple(tensor.shape)}")
    with torch.no_grad():
        for name, tensor in state.items():
            tensor.copy_(torch.as_tensor(np.asarray(weights[name]), dtype=tensor.dtype))


def count_parameters(net: nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())
