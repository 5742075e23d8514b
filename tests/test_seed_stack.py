"""Seeds side by side (training/seed_stack.py): a stacked seed trains as it would alone, seeds
do not leak into each other, checkpoints move between a stack and a lone run, evaluation
acts for all seeds in one forward, and the CUDA-graph driver's host-side logic (on CPU)."""

import copy
from dataclasses import asdict

import numpy as np
import pytest
import torch
from lerobot.configs import FeatureType, PolicyFeature

from lerobot_murm.features import goal_image_key, image_key
from lerobot_murm.policy.configuration_murm import MurmConfig
from lerobot_murm.policy.modeling_murm import MurmPolicy
from lerobot_murm.policy.replay import LatentReplay
from lerobot_murm.training.cuda_graph import Updates
from lerobot_murm.training.evaluate import act_together
from lerobot_murm.training.seed_stack import LoneSeed, SeedStack
from lerobot_murm.vqvae import VQVAEConfig
from lerobot_murm.vqvae.latent_cache import LatentCache

CAMERAS = ["global", "adjacent"]
ENCODER = VQVAEConfig(image_size=16, hidden_channels=8, residual_channels=4, codebook_size=16)
BATCH = 32
# fp32: seed k of a stack against the same seed alone, largest |difference| of any parameter
# relative to that parameter's largest magnitude, after 200 updates (measured 2e-7 for single
# view, 3e-7 for separated Q with view dropout: batched and plain matmuls sum in other orders)
TOLERANCE = 1e-5


@pytest.fixture(autouse=True)
def one_thread():
    """Tiny networks: one thread is fastest, and a busy machine cannot stall a second one."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def make_policies(seeds: list[int], method: str = "separated_q", **fields) -> list[MurmPolicy]:
    """Policies as a trainer builds them: initialisation drawn from the seed, one set of encoders."""
    cameras = CAMERAS[:1] if method == "single" else CAMERAS
    encoders = {c: asdict(VQVAEConfig(**asdict(ENCODER) | {"camera": c})) for c in cameras}
    image = PolicyFeature(type=FeatureType.VISUAL, shape=(3, 16, 16))
    config = MurmConfig(
        method=method,
        cameras=cameras,
        encoders=encoders,
        epsilon=[2.0] * len(cameras),
        hidden_units=16,
        precision="fp32",
        device="cpu",
        **fields,
    )
    config.input_features = {k: image for c in cameras for k in (image_key(c), goal_image_key(c))}
    config.output_features = {"action": PolicyFeature(type=FeatureType.ACTION, shape=(4,))}
    torch.manual_seed(99)
    trained_encoders = MurmPolicy(config).encoders.state_dict()  # loaded from one folder by every seed
    policies = []
    for seed in seeds:
        torch.manual_seed(seed)
        policies.append(MurmPolicy(copy.deepcopy(config)).train())
        policies[-1].encoders.load_state_dict(trained_encoders)
    return policies


def make_replay(policy: MurmPolicy, episodes: int = 20, frames: int = 25) -> LatentReplay:
    rng = np.random.default_rng(0)
    g, n = ENCODER.grid_size, episodes * frames
    caches = [
        LatentCache(
            c,
            rng.integers(0, 16, (n, g, g)).astype(np.uint16),
            rng.integers(0, 16, (episodes, g, g)).astype(np.uint16),
            rng.normal(size=(16, ENCODER.embedding_dim)).astype(np.float32),
            np.repeat(np.arange(episodes), frames),
            np.tile(np.arange(frames), episodes),
        )
        for c in policy.cameras
    ]
    c = policy.config
    replay = LatentReplay(
        caches,
        rng.uniform(-1, 1, (n, 4)).astype(np.float32),
        c.epsilon,
        c.her_ratio,
        dropout_p=c.dropout_p if c.view_dropout else 0.0,
    )
    policy.fit_latent_statistics(replay.latents)
    return replay


def train_alone(policy: MurmPolicy, replay: LatentReplay, seed: int, steps: int) -> list[float]:
    """The lone path `lerobot-train` takes: `forward`, one optimizer, `update`; the first loss."""
    optimizer = policy.config.get_optimizer_preset().build(policy.get_optim_params())
    generator = torch.Generator().manual_seed(seed)
    losses = []
    for _ in range(steps):
        loss, _ = policy.forward(replay.sample(BATCH, generator).transition())
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        policy.update()
        losses.append(loss.item())
    return losses


def relative_difference(a: MurmPolicy, b: MurmPolicy) -> float:
    own = dict(b.named_parameters())
    return max(((p - own[n]).abs().max() / p.abs().max().clamp(min=1e-12)).item() for n, p in a.named_parameters())


@pytest.mark.parametrize("method,fields", [("single", {}), ("separated_q", {"view_dropout": True})])
def test_a_stacked_seed_sees_the_batches_and_masks_it_would_alone(method, fields):
    replay = make_replay(make_policies([0], method, **fields)[0])
    generators = [torch.Generator().manual_seed(s) for s in (3, 4, 5)]
    stacked = replay.sample_stacked(BATCH, generators)
    for k, seed in enumerate((3, 4, 5)):
        alone = replay.sample(BATCH, torch.Generator().manual_seed(seed))
        for name, value in vars(alone).items():
            assert torch.equal(getattr(stacked, name)[k], value), name
    if fields:
        assert not stacked.keep.all()  # view dropout drew masks


@pytest.mark.parametrize("method,fields", [("single", {}), ("separated_q", {"view_dropout": True})])
def test_a_stacked_seed_trains_as_it_would_alone(method, fields):
    seeds = [0, 1, 2]
    stacked = make_policies(seeds, method, **fields)
    alone = make_policies([1], method, **fields)[0]
    replay = make_replay(stacked[0])
    alone.fit_latent_statistics(replay.latents)
    for policy in stacked[1:]:
        policy.fit_latent_statistics(replay.latents)
    assert relative_difference(stacked[1], alone) == 0  # the same initial weights
    stack = SeedStack(stacked)
    generators = [torch.Generator().manual_seed(s) for s in seeds]
    first_losses = stack.loss(replay.sample_stacked(BATCH, [torch.Generator().manual_seed(s) for s in seeds]))[0]
    losses = train_alone(alone, replay, seed=1, steps=200)
    torch.testing.assert_close(first_losses[1].item(), losses[0], rtol=1e-6, atol=0)
    for _ in range(200):
        stack.step(replay.sample_stacked(BATCH, generators))
    assert relative_difference(stack.write_back()[1], alone) < TOLERANCE


def test_changing_one_seeds_data_leaves_the_others_untouched():
    def trained(seeds_of_data: list[int]) -> list[MurmPolicy]:
        policies = make_policies([0, 1, 2], view_dropout=True)
        replay = make_replay(policies[0])
        for policy in policies[1:]:
            policy.fit_latent_statistics(replay.latents)
        stack = SeedStack(policies)
        generators = [torch.Generator().manual_seed(s) for s in seeds_of_data]
        for _ in range(20):
            stack.step(replay.sample_stacked(BATCH, generators))
        return stack.write_back()

    reference, changed = trained([0, 1, 2]), trained([0, 7, 2])
    for k in (0, 2):
        assert relative_difference(reference[k], changed[k]) == 0
    assert relative_difference(reference[1], changed[1]) > 0


def test_a_stack_resumes_from_lone_checkpoints_and_a_lone_run_from_a_stacks():
    policies = make_policies([0, 1])
    replay = make_replay(policies[0])
    policies[1].fit_latent_statistics(replay.latents)
    stack = SeedStack(policies)
    generators = [torch.Generator().manual_seed(s) for s in (0, 1)]
    for _ in range(5):
        stack.step(replay.sample_stacked(BATCH, generators))
    # checkpoints as the trainer writes them: each seed's weights and its lone optimizer state
    saved = [(copy.deepcopy(p.state_dict()), stack.optimizer_state(k)) for k, p in enumerate(stack.write_back())]
    saved_generators = [g.get_state() for g in generators]
    for _ in range(5):
        stack.step(replay.sample_stacked(BATCH, generators))
    continued = stack.write_back()

    resumed = make_policies([0, 1])
    for policy, (weights, _) in zip(resumed, saved, strict=True):
        policy.load_state_dict(weights)
    again = SeedStack(resumed)
    again.load_optimizer_states([state for _, state in saved])
    for g, state in zip(generators, saved_generators, strict=True):
        g.set_state(state)
    for _ in range(5):
        again.step(replay.sample_stacked(BATCH, generators))
    for a, b in zip(again.write_back(), continued, strict=True):
        assert relative_difference(a, b) == 0  # the stack resumed exactly

    alone = make_policies([1])[0]
    alone.load_state_dict(saved[1][0])
    lone = LoneSeed(alone)
    lone.load_optimizer_states([saved[1][1]])
    generator = torch.Generator()
    generator.set_state(saved_generators[1])
    for _ in range(5):
        lone.step(replay.sample_stacked(BATCH, [generator]))
    assert 0 < relative_difference(alone, continued[1]) < TOLERANCE  # one seed's checkpoint, trained on alone


def test_evaluation_acts_for_every_seed_in_one_forward_as_each_would_alone():
    policies = make_policies([0, 1, 2])
    make_replay(policies[0])
    for policy in policies:
        policy.eval().config.eval_mask_p = 0.5
    g = torch.Generator().manual_seed(0)
    batch = {
        key: torch.rand(3 * 4, 3, 16, 16, generator=g) for c in CAMERAS for key in (image_key(c), goal_image_key(c))
    }
    for policy in policies:
        policy.mask_generator.manual_seed(0)
    together = act_together(policies, batch)
    for k, policy in enumerate(policies):
        policy.mask_generator.manual_seed(0)  # each seed draws its masks as it would alone
        alone = policy.select_action({key: value[4 * k : 4 * (k + 1)] for key, value in batch.items()})
        torch.testing.assert_close(together[4 * k : 4 * (k + 1)], alone)
    # an evaluation encodes each episode's goal images once, at its reset: the very same actions
    goals = policies[0].goal_state(batch)
    without_goal_images = {image_key(c): batch[image_key(c)] for c in CAMERAS}
    for policy in policies:
        policy.mask_generator.manual_seed(0)
    assert torch.equal(act_together(policies, without_goal_images, goals=goals), together)


class FakeGraph:
    """CUDA graph stand-in: `capture` records the function without running it, `replay` runs it."""

    def __init__(self) -> None:
        self.captured, self.replays = None, 0

    def capture(self, fn) -> None:
        assert self.captured is None, "captured twice"
        self.captured = fn

    def replay(self) -> None:
        self.replays += 1
        self.captured()


def test_graphed_updates_warm_up_capture_once_replay_and_read_losses_back_every_n_steps():
    policies = make_policies([0, 1])
    replay = make_replay(policies[0])
    policies[1].fit_latent_statistics(replay.latents)
    eager_policies = copy.deepcopy(policies)

    def updates(policies: list[MurmPolicy], graph) -> tuple[Updates, SeedStack]:
        stack = SeedStack(policies)
        generators = [torch.Generator().manual_seed(s) for s in (0, 1)]
        return Updates(lambda: stack.step(replay.sample_stacked(BATCH, generators)), graph, warmup=3), stack

    graph = FakeGraph()
    graphed, graphed_stack = updates(policies, graph)
    eager, eager_stack = updates(eager_policies, None)
    means = []
    for step in range(1, 11):
        graphed()
        eager()
        if step % 5 == 0:
            means.append((graphed.read(), eager.read()))
    assert graph.replays == 7 and graphed.calls == 10  # 3 eager warm-up updates, then the graph
    for a, b in means:
        assert a.shape == (2, 7)
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    for a, b in zip(graphed_stack.write_back(), eager_stack.write_back(), strict=True):
        assert relative_difference(a, b) == 0
    with pytest.raises(RuntimeError, match="no update since the last read"):
        graphed.read()
