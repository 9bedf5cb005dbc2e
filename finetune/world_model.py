"""The dual-stream world model of fine-tuning (paper §4.3, appendix D.1), and its scratch twin.

Frozen stream (pre-trained encoder + ensemble RSSM, never updated), conditioned on the k = 1 temporal
embedding plus Gaussian noise where an action would enter:

    c_t  = Δt^e_{k=1} + ε_t,   ε_t ~ N(0, σ² I),  σ = 0.01      (Δt^e_{k=0} at a sequence's first step, from
                                                                  the zero state, as every pre-training sequence began)
    ŝ_t  ~ q_θ(ŝ_t | ŝ_{t−1}, c_t, enc(o_t))                       (the export's posterior)

New action-conditioned stream (trained from scratch, the same RSSM building block with one prior head):

    h̃_t = GRU(h̃_{t−1}, [s̃_{t−1}; a_{t−1}])
    prior      p_ψ(s̃_t | h̃_t, a_{t−1})     posterior   q_ψ(s̃_t | h̃_t, ŝ_t)     (ŝ_t enters as the frozen feature [deter; stoch])
    reward     R(s̃_t) = MLP(s̃_t)          decoder     D(s̃_t) → ô_t

Losses of the new stream (APV's stacked model is the reference: its action-conditioned stream has its own
posterior and prior tied by a KL term, and the decoder reconstructs o_t from that stream's state):

    L = − log N(o_t; D(s̃_t), 1) − log N(r_t; R(s̃_t), 1)
        + β [ α · max(KL(sg(q) ‖ p), free) + (1 − α) · max(KL(q ‖ sg(p)), free) ]       (α 0.8, β 1, free 1 nat)

Why these terms: the reconstruction is taken from s̃_t alone (not from [ŝ_t; s̃_t]) so that s̃_t must carry
what the frame shows; the reward head and imagination live in s̃, so a stream that could lean on ŝ_t for
the decoder would let s̃_t collapse onto its prior. The KL trains the action-conditioned prior to predict
what the posterior reads from ŝ_t, which is what makes action-conditioned imagination possible. The
decoder is a trainable copy of the export's (APV fine-tunes its pre-trained decoder), so the new stream's
deter + stoch must equal the export's (refused otherwise);
the frozen stream gets no loss at all.

Imagination: the frozen stream advances open-loop with its ensemble mean μ̄ = (1/M) Σ_i μ_i (as in
pre-training's open-loop prediction; it ignores actions), the new stream with the policy's actions,
sampling s̃_t from its prior so that gradients of returns reach the actions (dynamics backprop). The
imagined rewards are the reward head's R(s̃_t) unless a reward function of the whole rollout is passed
(offline RL's penalised reward, eq. 6; imitation's discriminator reward, eq. 5).

Prior heads (`model_heads`, 1 in the paper's online agent): offline RL gives the new stream M prior heads
on its one GRU, as pre-training's ensemble RSSM has. Every head is trained against the posterior with the
KL averaged over heads; imagination draws s̃_{t+1} from one random head per step and trajectory (LOMPO
draws one per step for the whole batch) or from N(mean of the heads' means, mean of their stds).

Scratch baseline (agent: scratch, DreamerV2-like with Gaussian latents): no frozen stream; a trainable
encoder feeds the posterior directly, and the policy sees s̃_t only.
"""

from __future__ import annotations

import contextlib
import copy
from collections.abc import Callable, Iterator
from typing import NamedTuple

import torch
from torch import nn

from finetune.behavior import ADAM_EPS, mlp
from finetune.config import FinetuneConfig
from finetune.pretrained import gap_embedding
from model.config import WorldModelConfig
from model.export import FrozenWorldModel
from model.losses import kl_halves, reconstruction_nll
from model.networks import Decoder, Encoder, preprocess
from model.rssm import EnsembleRSSM, RSSMState


class ExportSizeError(ValueError):
    """The config's sizes do not fit the frozen export the agent is built on."""


class Rollout(NamedTuple):
    """What imagination visited, handed to a reward function of it (H steps from N start states)."""

    feats: torch.Tensor  # [H+1, N, F]  z_0..z_H
    actions: torch.Tensor  # [H, N, A]  a_t, drawn by the policy at z_t
    new_feats: torch.Tensor  # [H, N, F~]  features of s̃_1..s̃_H
    new_stoch: torch.Tensor  # [H, N, S]  the sampled s̃_1..s̃_H
    prior_mean: torch.Tensor  # [H, M, N, S]  every prior head of the new stream at each step
    prior_std: torch.Tensor  # [H, M, N, S]
    frozen_means: torch.Tensor | None  # [H, M', N, S']  the frozen stream's heads (None for the scratch baseline)


# a reward function of an imagined rollout → rewards [H, N] (r_1..r_H); called where the world model's own
# parameters record no gradient, so that gradients reach only the policy's actions (dynamics backprop)
RewardFn = Callable[[Rollout], torch.Tensor]


class Latent(NamedTuple):
    """The agent's state: the frozen stream's ŝ (None for the scratch baseline) and the new stream's s̃."""

    frozen: RSSMState | None
    new: RSSMState

    def map(self, fn: Callable[[torch.Tensor], torch.Tensor]) -> Latent:
        """`fn` applied to every tensor (deter and stoch of both streams), e.g. a slice or `.detach()`."""
        return Latent(*(None if s is None else RSSMState(fn(s.deter), fn(s.stoch)) for s in self))


@contextlib.contextmanager
def no_param_grads(*modules: nn.Module) -> Iterator[None]:
    """Build graphs that reach the `modules`' outputs but record no gradients for their parameters."""
    params = [p for module in modules for p in module.parameters() if p.requires_grad]
    for p in params:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p in params:
            p.requires_grad_(True)


class DualStreamWorldModel(nn.Module):
    def __init__(self, cfg: FinetuneConfig, action_dim: int, frozen: FrozenWorldModel | None, k1_embedding: torch.Tensor | None):
        """`frozen`: the FrozenWorldModel from `finetune.load_pretrained` (None: scratch baseline) and its
        k = 1 temporal embedding [cond_dim]."""
        super().__init__()
        self.frozen = frozen
        self.noise_std = cfg.noise_std
        if frozen is not None:
            self.register_buffer("k1_embedding", k1_embedding.float().clone())
            self.register_buffer("start_embedding", gap_embedding(frozen, 0), persistent=False)  # from the export
            self.encoder = None  # the frozen one is used
            posterior_input = frozen.rssm.feature_dim
        else:
            self.encoder = Encoder(width=cfg.encoder_width, embed_dim=32 * cfg.encoder_width)
            posterior_input = self.encoder.embed_dim
        deter = cfg.deter or (frozen.rssm.deter_dim if frozen is not None else WorldModelConfig.deter)
        stoch = cfg.stoch or (frozen.rssm.stoch_dim if frozen is not None else WorldModelConfig.stoch)
        self.rssm = EnsembleRSSM(posterior_input, action_dim, deter, stoch, cfg.hidden, ensemble=cfg.model_heads)
        self.imagine_heads = cfg.imagine_heads
        self.decoder = self._decoder(cfg, frozen)
        self.reward = mlp(self.rssm.feature_dim, 1, cfg.units)
        self.kl_balance, self.kl_scale, self.free_nats = cfg.kl_balance, cfg.kl_scale, cfg.free_nats
        self.optimizer = torch.optim.Adam(self.trainable_parameters(), lr=cfg.model_lr, eps=ADAM_EPS)
        self.grad_clip = cfg.grad_clip
        self.conv_bf16 = cfg.conv_bf16

    def _decoder(self, cfg: FinetuneConfig, frozen: FrozenWorldModel | None) -> Decoder:
        if frozen is None:
            return Decoder(self.rssm.feature_dim, width=cfg.encoder_width)
        if frozen.decoder.feat_dim != self.rssm.feature_dim:
            raise ExportSizeError(
                f"the new stream's feature size deter+stoch = {self.rssm.feature_dim} must equal the export's "
                f"decoder input {frozen.decoder.feat_dim} so the decoder can start from the pre-trained one (APV); "
                f"leave deter/stoch unset in the config (they default to the export's sizes)")
        return copy.deepcopy(frozen.decoder).requires_grad_(True).train()  # a trainable copy; the export stays frozen

    def train(self, mode: bool = True) -> DualStreamWorldModel:
        super().train(mode)
        if self.frozen is not None:
            self.frozen.eval()  # the export stays in eval mode whatever the agent does
        return self

    def trainable_parameters(self) -> list[nn.Parameter]:
        """The new stream, decoder, reward head (and the scratch encoder): everything but the frozen export."""
        frozen_ids = {id(p) for p in self.frozen.parameters()} if self.frozen is not None else set()
        return [p for p in self.parameters() if id(p) not in frozen_ids]

    @property
    def feature_dim(self) -> int:
        """Size of the policy's input z_t = [ŝ_t; s̃_t] (s̃_t alone for the scratch baseline)."""
        frozen = self.frozen.rssm.feature_dim if self.frozen is not None else 0
        return frozen + self.rssm.feature_dim

    def feature(self, latent: Latent) -> torch.Tensor:
        new = self.rssm.feature(latent.new)
        return new if latent.frozen is None else torch.cat([self.frozen.rssm.feature(latent.frozen), new], -1)

    def frozen_cond(self, *shape: int) -> torch.Tensor:
        """c = Δt^e_{k=1} + N(0, σ²): the frozen stream's conditioning, fresh noise per call → [*shape, cond_dim]."""
        return self.with_noise(self.k1_embedding.expand(*shape, -1))

    def with_noise(self, embedding: torch.Tensor) -> torch.Tensor:
        return embedding + self.noise_std * torch.randn_like(embedding)

    def frozen_sequence_cond(self, batch: int, length: int) -> torch.Tensor:
        """The conditioning of a filtered window [B, L, cond_dim]: Δt^e_{k=0} at its first step (the frozen stream
        starts there from the zero state, like every pre-training sequence), Δt^e_{k=1} after; plus noise."""
        first = self.start_embedding.expand(batch, 1, -1)
        return self.with_noise(torch.cat([first, self.k1_embedding.expand(batch, length - 1, -1)], 1))

    def conv_precision(self) -> contextlib.AbstractContextManager:
        """bf16 autocast for the convolutional encoder and decoder when `conv_bf16` is set (a no-op otherwise)."""
        return torch.autocast(self.reward[0].weight.device.type, torch.bfloat16, enabled=self.conv_bf16)

    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """The image embedding (the frozen encoder's, or the scratch baseline's own) in float32: [..., E]."""
        with self.conv_precision():
            embed = (self.frozen.encoder if self.frozen is not None else self.encoder)(images)
        return embed.float()

    # -- filtering real sequences -------------------------------------------------------------------

    def observe(self, obs: torch.Tensor, actions: torch.Tensor) -> tuple[Latent, tuple[torch.Tensor, ...]]:
        """obs uint8 [B, L, 3, 64, 64], actions [B, L, A] (a_{t−1} at t) → posterior latents [B, L, ·] and the
        new stream's (post mean, post std [B, L, S], prior means, prior stds of every head [M, B, L, S])."""
        batch, length = obs.shape[:2]
        images = preprocess(obs)
        if self.frozen is not None:
            with torch.no_grad():
                frozen = self.frozen.rssm.observe(self.encode(images), self.frozen_sequence_cond(batch, length))
            frozen_state = RSSMState(frozen.deter, frozen.stoch)
            posterior_input = self.frozen.rssm.feature(frozen_state)  # [B, L, F̂], F̂ = the export's feature_dim
        else:
            frozen_state, posterior_input = None, self.encode(images)
        new = self.rssm.observe(posterior_input, actions)
        dists = (new.post_mean, new.post_std, new.prior_mean, new.prior_std)
        return Latent(frozen_state, RSSMState(new.deter, new.stoch)), dists

    def loss(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, Latent, dict[str, torch.Tensor]]:
        """The loss of the new parts on a replay batch, the posterior latents, and detached metrics (no host sync)."""
        latent, (post_mean, post_std, prior_mean, prior_std) = self.observe(batch["obs"], batch["action"])
        feat = self.rssm.feature(latent.new)  # [B, L, F~]
        with self.conv_precision():
            recon = self.decoder(feat)  # [B, L, 3, 64, 64] (bf16 under conv_bf16; the NLL upcasts it)
        recon_nll = reconstruction_nll(recon, preprocess(batch["obs"])).mean()
        if "reward" in batch:
            reward_nll = 0.5 * (self.reward(feat).squeeze(-1) - batch["reward"]).pow(2).mean()
        else:  # imitation: no environment reward is ever learned from
            reward_nll = feat.new_zeros(())
        # every head against the posterior, averaged over heads, batch and time ([M, B, L] → scalar), then free nats
        kl_prior, kl_post = (half.mean() for half in kl_halves(post_mean, post_std, prior_mean, prior_std))
        kl = self.kl_balance * kl_prior.clamp(min=self.free_nats) + (1 - self.kl_balance) * kl_post.clamp(min=self.free_nats)
        loss = recon_nll + reward_nll + self.kl_scale * kl
        metrics = {"model_loss": loss, "recon_nll": recon_nll, "reward_nll": reward_nll, "kl": kl_post}
        return loss, latent, {name: value.detach() for name, value in metrics.items()}

    def step(self, loss: torch.Tensor, latent: Latent, metrics: dict[str, torch.Tensor]) -> tuple[Latent, dict[str, torch.Tensor]]:
        """Backward, clip and Adam step on the result of `loss` (which the agent may run compiled)."""
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        metrics["model_grad_norm"] = nn.utils.clip_grad_norm_(self.trainable_parameters(), self.grad_clip)
        self.optimizer.step()
        return latent.map(torch.Tensor.detach), metrics

    # -- acting and imagining -----------------------------------------------------------------------

    def initial(self, batch_size: int, device: torch.device) -> Latent:
        frozen = self.frozen.rssm.initial(batch_size, device) if self.frozen is not None else None
        return Latent(frozen, self.rssm.initial(batch_size, device))

    @torch.no_grad()
    def observe_step(self, latent: Latent, prev_action: torch.Tensor, obs: torch.Tensor) -> Latent:
        """Filter one real step while acting: obs uint8 [B, 3, 64, 64], prev_action [B, A]."""
        images = preprocess(obs)
        if self.frozen is not None:
            first = (latent.frozen.deter == 0).all(-1, keepdim=True)  # [B, 1]: an episode's first step (the zero state)
            cond = self.with_noise(torch.where(first, self.start_embedding, self.k1_embedding))
            frozen = self.frozen.rssm.obs_step(latent.frozen, cond, self.encode(images))[0]
            posterior_input = self.frozen.rssm.feature(frozen)
        else:
            frozen, posterior_input = None, self.encode(images)
        new = self.rssm.obs_step(latent.new, prev_action, posterior_input)[0]
        return Latent(frozen, new)

    def next_stoch(self, mean: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
        """Sample s̃_{t+1} from the prior heads mean, std [M, N, S] → [N, S] (reparameterised): the one head when
        M = 1; else a random head per trajectory (`imagine_heads: random`) or N(mean of means, mean of stds)."""
        if mean.shape[0] == 1:
            mean, std = mean[0], std[0]
        elif self.imagine_heads == "mean":
            mean, std = mean.mean(0), std.mean(0)
        else:
            pick = torch.randint(mean.shape[0], (1, mean.shape[1], 1), device=mean.device).expand(1, *mean.shape[1:])
            mean, std = mean.gather(0, pick)[0], std.gather(0, pick)[0]
        return mean + std * torch.randn_like(std)

    def imagine(self, start: Latent, policy: Callable, horizon: int,
                reward: RewardFn | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Roll out `horizon` steps from every start state ([B, L, ·] flattened to N = B·L).

        Returns feats z_0..z_H [H+1, N, F], rewards [H, N] and the policy's entropies [H, N] (H ≥ 0). The rewards are
        the reward head's R(s̃_1..s̃_H), or `reward(rollout)` when given. Gradients reach the policy through the
        new stream's transitions and the reward, whose own parameters record no gradient here (the world
        model's are trained by the model loss only; a reward function guards its own).
        """
        flat = start.map(lambda x: x.flatten(0, 1))
        frozen, new = flat
        feats, new_feats, entropies = [self.feature(flat)], [], []
        actions, stochs, means, stds, frozen_means = [], [], [], [], []
        with no_param_grads(self):
            for _ in range(horizon):
                dist = policy(feats[-1].detach())
                action = dist.rsample()  # [N, A]
                entropies.append(dist.entropy())
                if frozen is not None:
                    with torch.no_grad():
                        deter, heads, _ = self.frozen.rssm.img_step(frozen, self.frozen_cond(action.shape[0]))
                        frozen = RSSMState(deter, heads.mean(0))  # ensemble mean μ̄
                    frozen_means.append(heads)
                deter, mean, std = self.rssm.img_step(new, action)  # mean, std [M, N, S]
                new = RSSMState(deter, self.next_stoch(mean, std))
                new_feats.append(self.rssm.feature(new))
                feats.append(self.feature(Latent(frozen, new)))
                actions.append(action)
                stochs.append(new.stoch)
                means.append(mean)
                stds.append(std)
            if horizon == 0:  # the start states alone
                nothing = feats[0].new_zeros(0, feats[0].shape[0])
                return torch.stack(feats), nothing, nothing
            if reward is None:
                rewards = self.predicted_reward(torch.stack(new_feats))  # [H, N]
            else:
                rollout = Rollout(torch.stack(feats), torch.stack(actions), torch.stack(new_feats), torch.stack(stochs),
                                  torch.stack(means), torch.stack(stds), torch.stack(frozen_means) if frozen_means else None)
                rewards = reward(rollout)
        return torch.stack(feats), rewards, torch.stack(entropies)

    def predicted_reward(self, new_feats: torch.Tensor) -> torch.Tensor:
        """The reward head R(s̃) on new-stream features [..., F~] → [...]."""
        return self.reward(new_feats).squeeze(-1)
