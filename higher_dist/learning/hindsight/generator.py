"""The instruction generator of HIGhER: view before the final pick -> the instruction it fulfilled.

`InstructionGenerator` encodes ONE 7x7x4 view (on a level whose missions name locations, also where the
object in front lay seen from the start: `WorldSpec.start_locations`) and decodes words with a GRU; `GeneratorTrainer`
owns the model, its optimizer and its dataset (`generator_data.GeneratorDataset`), trains it by
teacher-forced cross-entropy, measures validation accuracy semantically (the described object,
not the surface words) and decides when the generator may be trusted (the gate).

Token conventions (docs/architecture.md): a mission is `(MISSION_LEN,)` word ids PAD-padded, without
BEG/END; the decoder reads `BEG w1..wn` and is trained to emit `w1..wn END`.
"""
from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from higher_dist.config import GeneratorConfig
from higher_dist.learning.episode import Episode
from higher_dist.learning.devices import resolve_device
from higher_dist.learning.exploration import linear_schedule
from higher_dist.learning.hindsight.generator_data import GeneratorDataset, semantic_accuracy
from higher_dist.learning.networks import ViewEncoder
from higher_dist.learning.seeds import RelabelerSeeds
from higher_dist.world.spec import DEFAULT_SPEC, WorldSpec
from higher_dist.world.babyai_language import LOC_MASKS
from higher_dist.world.language import BEG, END, PAD

GRAD_CLIP = 5.0  # GRU decoders occasionally spike early in training; clipping keeps Adam steady
EVAL_CHUNK = 1024  # validation is decoded in chunks to bound memory


def front_cell(view_size: int) -> tuple[int, int]:
    """(row, col) of the cell the agent faces, where a picked object lies: the agent is at the bottom
    centre (row V-1, column V//2) facing up, so the cell in front is (V-2, V//2)."""
    return view_size - 2, view_size // 2


class InstructionGenerator(nn.Module):
    """Conv encoder of one view + GRU decoder over the vocabulary.

    The encoder is the Q-network's `ViewEncoder` (per-channel embeddings summed, then 3x3 convs).
    Besides the conv features, the front cell's per-channel embeddings (the same table's rows, one per
    channel, side by side rather than summed) are fed straight into the context vector: the object to
    describe is always there, and a direct path that keeps its attributes apart lets the decoder read
    each one independently of the others, which is what makes it describe attribute combinations it
    never saw (the held-out goals) and learn from few pairs (docs/decisions.md, "The generator sees the
    cell in front"). The conv path still sees the whole view (walls, distractors) as in the paper.

    A mission that names a location ("the door on your left") speaks of where the agent started, which
    no single view shows. On such levels the context also gets an embedding of the front cell's location
    mask seen from the start (`where`, 0..15), reckoned from the episode's own frames and actions.
    """

    def __init__(self, cfg: GeneratorConfig, spec: WorldSpec = DEFAULT_SPEC):
        super().__init__()
        vocab_size = spec.vocab_size
        self.cfg, self.vocab_size, self.view_size = cfg, int(vocab_size), spec.view_size
        self.mission_len = spec.mission_len
        self.front = front_cell(spec.view_size)
        self.encoder = ViewEncoder(cfg.embed_dim, tuple(cfg.conv_channels), in_frames=1, spec=spec)
        self.shortcut = bool(cfg.front_cell_shortcut)  # off: the paper's generator, conv features only
        cell_dim = len(spec.channel_values) * cfg.embed_dim  # the front cell's channel rows, side by side
        self.context = nn.Linear(self.encoder.out_dim + (cell_dim if self.shortcut else 0), cfg.hidden)
        self.where = nn.Embedding(LOC_MASKS, cfg.hidden) if spec.has_locations else None
        self.init_hidden = nn.Linear(cfg.hidden, cfg.hidden)
        self.word_embed = nn.Embedding(vocab_size, cfg.word_embed_dim, padding_idx=PAD)
        # The context is fed at every step as well as through the initial state, so the decoder never
        # has to carry the object's attributes across the prefix words in its state alone.
        self.gru = nn.GRU(cfg.word_embed_dim + cfg.hidden, cfg.hidden, batch_first=True)
        self.out = nn.Linear(cfg.hidden, vocab_size)
        # PAD and BEG are never emitted: PAD would end a mission early without END, BEG is input only.
        banned = torch.zeros(vocab_size, dtype=torch.bool)
        banned[[PAD, BEG]] = True
        self.register_buffer("banned", banned, persistent=False)

    def encode(self, views: torch.Tensor, where: torch.Tensor | None = None) -> torch.Tensor:
        """(B, V, V, 4) integer views (and (B,) location masks where the level names locations; None: 0)
        -> (B, hidden) context."""
        if views.dim() != 4 or views.shape[1:] != (self.view_size, self.view_size, 4):
            raise ValueError(f"views: expected (B, {self.view_size}, {self.view_size}, 4), got {tuple(views.shape)}")
        stacked = views[:, None]  # a "stack" of one frame, as the encoder takes
        maps = self.encoder(stacked).flatten(1)
        if self.shortcut:
            r, c = self.front
            # The front cell through the same (shared) table, one row per channel.
            maps = torch.cat([maps, self.encoder.channel_embeddings(views[:, r, c, :])], dim=1)
        ctx = self.context(maps)
        if self.where is not None:
            ctx = ctx + self.where(torch.zeros_like(views[:, 0, 0, 0], dtype=torch.long) if where is None
                                   else where.long())
        return F.relu(ctx)

    def _step(self, tokens: torch.Tensor, ctx: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Inputs (B, T) tokens -> logits (B, T, vocab) and the new hidden state."""
        x = torch.cat([self.word_embed(tokens), ctx[:, None].expand(-1, tokens.shape[1], -1)], dim=2)
        out, h = self.gru(x, h)
        return self.out(out), h

    def forward(self, views: torch.Tensor, missions: torch.Tensor, where: torch.Tensor | None = None) -> torch.Tensor:
        """Teacher-forced logits (B, L+1, vocab) for the targets `w1..wn END` given inputs `BEG w1..wn`."""
        ctx = self.encode(views, where)
        h0 = torch.tanh(self.init_hidden(ctx))[None]
        inputs = torch.cat([torch.full_like(missions[:, :1], BEG), missions], dim=1)
        logits, _ = self._step(inputs, ctx, h0)
        return logits

    def loss(self, views: torch.Tensor, missions: torch.Tensor, where: torch.Tensor | None = None) -> torch.Tensor:
        """Mean cross-entropy over the real target tokens (words and END; PAD ignored)."""
        return F.cross_entropy(self(views, missions, where).flatten(0, 1), decoder_targets(missions).flatten(),
                               ignore_index=PAD)

    @torch.no_grad()
    def _decode(self, views: torch.Tensor, max_len: int, choose, where: torch.Tensor | None) -> torch.Tensor:
        b = views.shape[0]
        ctx = self.encode(views, where)
        h = torch.tanh(self.init_hidden(ctx))[None]
        token = torch.full((b, 1), BEG, dtype=torch.long, device=views.device)
        words = torch.full((b, max(max_len, self.mission_len)), PAD, dtype=torch.long, device=views.device)
        done = torch.zeros(b, dtype=torch.bool, device=views.device)
        for t in range(max_len):
            logits, h = self._step(token, ctx, h)
            logits = logits[:, 0].masked_fill(self.banned, -math.inf)
            nxt = choose(logits)
            done = done | (nxt == END)
            # A finished row keeps PAD; END itself is not part of the mission encoding.
            words[:, t] = torch.where(done, torch.full_like(nxt, PAD), nxt)
            if bool(done.all()):
                break
            token = nxt[:, None]
        # An output that never ended is cut to the mission length; the parser judges it.
        return words[:, :self.mission_len]

    def greedy(self, views: torch.Tensor, max_len: int | None = None, where: torch.Tensor | None = None) -> torch.Tensor:
        """(B, MISSION_LEN) int64 word tokens, PAD-padded; at most `max_len` decoding steps."""
        return self._decode(views, self.cfg.max_len if max_len is None else max_len,
                            lambda logits: logits.argmax(dim=1), where)

    def sample(self, views: torch.Tensor, max_len: int | None = None,
               generator: torch.Generator | None = None, temperature: float = 1.0,
               where: torch.Tensor | None = None, top_p: float = 1.0) -> torch.Tensor:
        """Like `greedy` but each word is drawn from softmax(logits / temperature), among the fewest
        likeliest words whose probabilities sum to at least `top_p` (nucleus sampling): words the
        generator finds about equally likely (phrasings) stay a draw, a word it is sure of is kept."""
        if temperature <= 0:
            return self.greedy(views, max_len, where)

        def choose(logits: torch.Tensor) -> torch.Tensor:
            probs = torch.softmax(logits / temperature, dim=1)
            if top_p < 1.0:
                probs = nucleus(probs, top_p)
            return torch.multinomial(probs, 1, generator=generator)[:, 0]

        return self._decode(views, self.cfg.max_len if max_len is None else max_len, choose, where)

    @torch.no_grad()
    def beam(self, views: torch.Tensor, width: int, where: torch.Tensor | None = None
             ) -> tuple[torch.Tensor, torch.Tensor]:
        """Beam search: the `width` likeliest instructions found for each view, (B, width, MISSION_LEN)
        words PAD-padded, and their log-probabilities (B, width), likeliest first. A beam that has
        emitted END goes on with PAD at no cost, so finished and unfinished beams compete on one score."""
        b, vocab, max_len = views.shape[0], self.vocab_size, self.cfg.max_len
        ctx = self.encode(views, where).repeat_interleave(width, 0)
        h = torch.tanh(self.init_hidden(ctx))[None]
        token = torch.full((b * width, 1), BEG, dtype=torch.long, device=views.device)
        scores = torch.full((b, width), -math.inf, device=views.device)
        scores[:, 0] = 0.0  # one live beam at the start: the others would repeat it
        words = torch.full((b, width, max(max_len, self.mission_len)), PAD, dtype=torch.long, device=views.device)
        done = torch.zeros(b, width, dtype=torch.bool, device=views.device)
        pad_only = torch.where(torch.arange(vocab, device=views.device) == PAD, 0.0, -math.inf)  # a finished beam's step
        for t in range(max_len):
            logits, h = self._step(token, ctx, h)
            logp = F.log_softmax(logits[:, 0].masked_fill(self.banned, -math.inf), dim=1).view(b, width, vocab)
            logp = torch.where(done[..., None], pad_only, logp)
            scores, flat = (scores[..., None] + logp).view(b, width * vocab).topk(width, dim=1)
            source, nxt = flat // vocab, flat % vocab
            words, done = words.gather(1, source[..., None].expand_as(words)), done.gather(1, source)
            words[:, :, t] = torch.where(done | (nxt == END), torch.full_like(nxt, PAD), nxt)
            done = done | (nxt == END)
            h = h.view(1, b, width, -1).gather(2, source[None, ..., None].expand(1, b, width, h.shape[-1]))
            h, token = h.view(1, b * width, -1), nxt.view(-1, 1)
            if bool(done.all()):
                break
        return words[:, :, :self.mission_len], scores


def nucleus(probs: torch.Tensor, top_p: float) -> torch.Tensor:
    """(B, V) probabilities with every word outside each row's nucleus zeroed: the likeliest words, in
    order, up to and including the first at which their running sum reaches `top_p`."""
    sorted_probs, order = probs.sort(dim=1, descending=True)
    before = sorted_probs.cumsum(dim=1) - sorted_probs  # mass of the likelier words
    keep_sorted = before < top_p  # the likeliest word always stays (nothing before it)
    keep = torch.zeros_like(keep_sorted).scatter(1, order, keep_sorted)
    return probs * keep


def decoder_targets(missions: torch.Tensor) -> torch.Tensor:
    """(B, L) PAD-padded words -> (B, L+1) targets `w1..wn END PAD..`."""
    lengths = (missions != PAD).sum(dim=1)
    targets = torch.cat([missions, torch.full_like(missions[:, :1], PAD)], dim=1)
    targets[torch.arange(missions.shape[0], device=missions.device), lengths] = END
    return targets


def generator_lr(cfg: GeneratorConfig, steps: int) -> float:
    """Adam's learning rate for the generator's update number `steps`: cfg.lr, falling linearly to
    cfg.lr * lr_end_fraction over cfg.lr_decay_updates updates when that is > 0. Counted in updates, not
    frames: the generator's pace per frame is set apart (updates_per_kframe), and its data grows with them."""
    if cfg.lr_decay_updates <= 0:
        return cfg.lr
    return linear_schedule(steps, cfg.lr, cfg.lr * cfg.lr_end_fraction, cfg.lr_decay_updates)


def inference_batch(n: int) -> int:
    """The batch size `n` views are padded to for greedy decoding: the next power of two, at least 8 and
    at most EVAL_CHUNK, so decoding only ever sees a handful of shapes."""
    return min(EVAL_CHUNK, max(8, 1 << (max(n, 1) - 1).bit_length()))


class GeneratorTrainer:
    """Model + Adam + dataset, with the gate that says when the generator may relabel."""

    def __init__(self, cfg: GeneratorConfig, spec: WorldSpec = DEFAULT_SPEC, seed: int | RelabelerSeeds = 0,
                 device: str = "cpu"):
        """`seed`: the relabeler's streams (Seeds.relabeler), or a run seed standing for its streams."""
        self.cfg, self.device, self.spec, self.language = cfg, resolve_device(device), spec, spec.language
        seeds = RelabelerSeeds.of(seed)
        # A private RNG stream for the initial weights: building a trainer leaves the global torch
        # RNG untouched, and two trainers with one seed start identical.
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seeds.generator_init)
            self.model = InstructionGenerator(cfg, spec).to(self.device)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=cfg.lr)
        self.dataset = GeneratorDataset(cfg.capacity, cfg.val_fraction, seeds.dataset_split, spec)
        self.rng = np.random.default_rng(seeds.generator_batches)
        self.steps = 0  # gradient steps taken
        self.evaluations = 0
        self.val_accuracy = 0.0  # exact match at the last evaluate(); 0 until the first one
        self.last_eval: dict[str, float] = {}
        self.val_at_pairs = 0  # dataset size (pairs) when val_accuracy was measured
        self.last_loss = float("nan")

    def observe_episodes(self, episodes: list[Episode]) -> int:
        """Add the pairs of the successful original episodes; returns how many were kept."""
        return sum(self.dataset.add_episode(ep) for ep in episodes)

    def train_steps(self, n: int) -> float:
        """`n` Adam steps on minibatches of training pairs; mean loss (nan if nothing to train on)."""
        if n <= 0 or self.dataset.n_train == 0:
            return float("nan")
        self.model.train()
        total = 0.0
        for i in range(n):
            if self.cfg.lr_decay_updates > 0:
                for group in self.optimizer.param_groups:
                    group["lr"] = generator_lr(self.cfg, self.steps + i)
            views, tokens, where = self.dataset.sample_train(self.cfg.batch_size, self.rng)
            loss = self.model.loss(torch.as_tensor(views, device=self.device),
                                   torch.as_tensor(tokens, device=self.device),
                                   torch.as_tensor(where, device=self.device))
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            nn.utils.clip_grad_norm_(self.model.parameters(), GRAD_CLIP)
            self.optimizer.step()
            total += float(loss.detach())
        self.steps += n
        self.last_loss = total / n
        return self.last_loss

    def generate(self, views: np.ndarray, where: np.ndarray | None = None, seed: int | None = None) -> np.ndarray:
        """Instructions (N, MISSION_LEN) int64 for (N, V, V, 4) views and, on a level whose missions
        name locations, their (N,) `WorldSpec.start_locations` (None: 0, nowhere known). Greedy, or with
        `seed` each word drawn from the generator's distribution (a torch generator seeded with it).
        With `beam_width` > 1, a greedy output that names no object is replaced by the likeliest of the
        beam's instructions that does (kept where none does: the parser judges it downstream)."""
        views = np.asarray(views)
        if views.shape[0] == 0:
            return np.zeros((0, self.model.mission_len), np.int64)
        where = np.zeros(len(views), np.int64) if where is None else np.asarray(where, np.int64)
        self.model.eval()
        if seed is not None:
            draws = torch.Generator(device=self.device).manual_seed(int(seed))
            return self._decode_padded(views, where, lambda inputs, at: self.model.sample(
                inputs, generator=draws, temperature=self.cfg.temperature, where=at, top_p=self.cfg.top_p))
        words = self._decode_padded(views, where, lambda inputs, at: self.model.greedy(inputs, where=at))
        if self.cfg.beam_width > 1:
            # Only outputs that do not parse are searched again: a trained generator's almost all parse.
            redo = np.flatnonzero(~self.language.parse_many(words)[1])
            if redo.size:
                searched = self._decode_padded(views[redo], where[redo], lambda inputs, at: self._likeliest_parsed(
                    *self.model.beam(inputs, self.cfg.beam_width, where=at)))
                found = self.language.parse_many(searched)[1]
                words[redo[found]] = searched[found]
        return words

    def _decode_padded(self, views: np.ndarray, where: np.ndarray, decode) -> np.ndarray:
        """`decode(views, where)` over chunks of at most EVAL_CHUNK views, each padded to one of a few
        fixed batch sizes: the CPU kernels cache per input shape, and the relabeler sees every batch size
        from 1 up, which grew its memory by ~70 MiB before it levelled off."""
        chunks = []
        for i in range(0, views.shape[0], EVAL_CHUNK):
            chunk = views[i:i + EVAL_CHUNK]
            padded = np.zeros((inference_batch(len(chunk)), *chunk.shape[1:]), chunk.dtype)
            padded[: len(chunk)] = chunk
            padded_where = np.zeros(len(padded), np.int64)
            padded_where[: len(chunk)] = where[i:i + EVAL_CHUNK]
            out = decode(torch.as_tensor(padded, device=self.device), torch.as_tensor(padded_where, device=self.device))
            chunks.append(out.cpu().numpy()[: len(chunk)])
        return np.concatenate(chunks).astype(np.int64)

    def _likeliest_parsed(self, beams: torch.Tensor, scores: torch.Tensor) -> torch.Tensor:
        """(B, W, L) beams and their (B, W) scores -> (B, L): per view the likeliest beam that names an
        object (the parser every relabel passes through), the likeliest beam where none does."""
        b, width, length = beams.shape
        _, ok = self.language.parse_many(beams.reshape(b * width, length).cpu().numpy())
        ok = torch.as_tensor(ok.reshape(b, width), device=beams.device)
        pick = torch.where(ok, scores, torch.full_like(scores, -math.inf)).argmax(dim=1)
        pick = torch.where(ok.any(dim=1), pick, torch.zeros_like(pick))
        return beams[torch.arange(b, device=beams.device), pick]

    def describe(self, views: np.ndarray, where: np.ndarray | None, seed: int, rephrase: bool = False,
                 draws: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Relabel instructions for (N, V, V, 4) views, and how sure the generator is of what they name.

        Returns (instructions (N, MISSION_LEN), agreement (N,)). The instructions name the object of the
        greedy words. `agreement` is the share of `draws` instructions drawn from the generator (seeds
        from `seed`) that name that object, among the draws that parse; 0 where none parses, 1.0
        everywhere when `draws` is 0. Greedy decoding picks each word alone; the share says how much of
        the generator's probability, summed over every phrasing, lies on its object. A draw that names
        no object is left out of the share: it says the generator's grammar is unsure, not what it sees.
        `rephrase`: each instruction is the first draw that names the greedy object (one draw is made
        when `draws` is 0), the greedy words where none does."""
        greedy = self.generate(views, where)
        if not draws and not rephrase:  # the default path: nothing to draw, nothing to parse here
            return greedy, np.ones(len(greedy))
        attrs, ok = self.language.parse_many(greedy)
        words, phrased = greedy.copy(), np.zeros(len(greedy), bool)
        agreeing, parsed = np.zeros(len(greedy)), np.zeros(len(greedy))
        seeds = np.random.default_rng(seed).integers(2 ** 63, size=max(draws, int(rephrase)))
        for draw_seed in seeds:
            drawn = self.generate(views, where, seed=int(draw_seed))
            drawn_attrs, drawn_ok = self.language.parse_many(drawn)
            same = ok & drawn_ok & (drawn_attrs == attrs).all(axis=1)
            agreeing += same
            parsed += drawn_ok
            if rephrase:
                first = same & ~phrased
                words[first] = drawn[first]
                phrased |= same
        if not draws:
            return words, np.ones(len(greedy))
        return words, np.divide(agreeing, parsed, out=np.zeros(len(greedy)), where=parsed > 0)

    def evaluate_pairs(self, views: np.ndarray, tokens: np.ndarray, where: np.ndarray | None = None) -> dict[str, float]:
        """Semantic accuracy of the greedy outputs on given pairs: do they describe the object the pair's
        mission was fulfilled by (`WorldSpec.fulfilled_by`, with the pairs' start locations where known)?"""
        true_attrs = self.spec.fulfilled_by(views, tokens, where)
        return semantic_accuracy(self.generate(views, where), true_attrs, self.language)

    def evaluate(self) -> dict[str, float]:
        """Accuracy on the validation split; its exact match becomes `val_accuracy` (the gate's input)."""
        result = self.evaluate_pairs(*self.dataset.validation())
        self.val_accuracy = result["exact"]
        self.val_at_pairs = len(self.dataset)
        self.last_eval = result
        self.evaluations += 1
        return result

    @property
    def gate_open(self) -> bool:
        """Enough pairs, and (unless min_accuracy is 0, the paper's ungated variant) accurate enough."""
        if len(self.dataset) < self.cfg.n_min:
            return False
        return self.cfg.min_accuracy <= 0 or self.val_accuracy >= self.cfg.min_accuracy

    def state_dict(self) -> dict[str, Any]:
        """A snapshot for checkpoints. Deep-copied: torch's state dicts alias the live tensors (and
        Adam's moments would be shared with whatever loads them), a snapshot must not move."""
        return {"model": copy.deepcopy(self.model.state_dict()),
                "optimizer": copy.deepcopy(self.optimizer.state_dict()),
                "dataset": self.dataset.state_dict(), "rng": self.rng.bit_generator.state,
                "steps": self.steps, "evaluations": self.evaluations, "val_accuracy": self.val_accuracy,
                "val_at_pairs": self.val_at_pairs, "last_eval": dict(self.last_eval), "last_loss": self.last_loss}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.dataset.load_state_dict(state["dataset"])
        self.rng.bit_generator.state = state["rng"]
        self.steps, self.evaluations = int(state["steps"]), int(state["evaluations"])
        self.val_accuracy = float(state["val_accuracy"])
        self.val_at_pairs = int(state.get("val_at_pairs", 0))
        self.last_eval = dict(state["last_eval"])
        self.last_loss = float(state["last_loss"])
