"""Mixed precision of IQL's losses: which precision `auto` picks, that `bf16` really runs the
hidden layers' matmuls in bf16 while outputs, losses and parameters stay fp32, and that it
changes neither the losses and gradients of a batch (within bf16's rounding) nor learning."""

from dataclasses import asdict

import pytest
import torch
from lerobot.configs import FeatureType, PolicyFeature

from lerobot_murm.policy.configuration_murm import MurmConfig
from lerobot_murm.policy.modeling_murm import MurmPolicy
from lerobot_murm.policy.precision import cpu_description, cpu_has_native_bf16, resolve_precision
from lerobot_murm.policy.replay import (
    TRANSITION_ACTION as ACTION,
    TRANSITION_DONE as DONE,
    TRANSITION_NEXT_STATE as NEXT_STATE,
    TRANSITION_REWARD as REWARD,
    TRANSITION_STATE as STATE,
)
from lerobot_murm.vqvae import VQVAEConfig

CAMERAS = ["global", "adjacent"]
EPYC_FLAGS = "processor\t: 0\nflags\t\t: fpu sse avx2 avx512f avx512_bf16 avx512_vnni\n"
XEON_AMX_FLAGS = "flags\t\t: fpu avx512f amx_bf16 amx_tile amx_int8\n"
OLD_FLAGS = "flags\t\t: fpu sse avx2 avx512f avx512_vnni\nbugs\t\t: avx512_bf16_is_a_bug_name_not_a_flag\n"


@pytest.fixture(autouse=True)
def one_thread():
    """These small matmuls gain nothing from a second thread, and on a machine shared with other
    jobs OpenMP's waiting threads made this file 20x slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def make_policy(method: str = "separated_q", image_size: int = 48, **fields) -> MurmPolicy:
    """A policy on the latents of 48x48 encoders (720 numbers) or smaller ones, built without any file."""
    encoders = {c: asdict(VQVAEConfig(camera=c, image_size=image_size)) for c in CAMERAS}
    config = MurmConfig(method=method, cameras=CAMERAS, encoders=encoders, epsilon=[2.0, 2.0], **fields)
    config.output_features = {"action": PolicyFeature(type=FeatureType.ACTION, shape=(4,))}
    torch.manual_seed(0)
    return MurmPolicy(config).train()


def transitions(size: int, seed: int, latent_dim: int = 720) -> dict[str, torch.Tensor]:
    """Standardised-scale latents whose action and reward depend on the state, so there is
    something to learn: the action is a function of the first camera's latent, the reward
    counts the cameras whose first feature is positive."""
    g = torch.Generator().manual_seed(seed)
    state = torch.randn(size, len(CAMERAS), 2 * latent_dim, generator=g)
    next_state = state + 0.1 * torch.randn(state.shape, generator=g)
    return {
        STATE: state,
        NEXT_STATE: next_state,
        ACTION: torch.tanh(state[:, 0, :4] + state[:, 1, 4:8]),
        REWARD: (next_state[:, :, 0] > 0).float().sum(1) - len(CAMERAS),
        DONE: torch.zeros(size),
    }


def loss_and_gradients(policy: MurmPolicy, batch: dict) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    policy.zero_grad(set_to_none=True)
    loss, _ = policy.forward(batch)
    loss.backward()
    gradients = {
        name: torch.cat([p.grad.flatten() for p in getattr(policy, name).parameters()])
        for name in ("critic", "value", "actor")
    }
    return loss.detach(), gradients


def test_auto_picks_bf16_only_where_it_trains_faster():
    assert cpu_has_native_bf16(EPYC_FLAGS) and cpu_has_native_bf16(XEON_AMX_FLAGS)
    assert not cpu_has_native_bf16(OLD_FLAGS) and not cpu_has_native_bf16("")
    cpu = torch.device("cpu")
    assert resolve_precision("fp32", cpu) == torch.float32 and resolve_precision("bf16", cpu) == torch.bfloat16
    with open("/proc/cpuinfo") as f:
        native = cpu_has_native_bf16(f.read())
    assert resolve_precision("auto", cpu) == (torch.bfloat16 if native else torch.float32)
    assert resolve_precision("auto", torch.device("mps")) == torch.float32
    assert resolve_precision("auto", torch.device("cuda")) == torch.float32  # launch-bound: bf16 measured slower
    with pytest.raises(ValueError, match="unknown precision 'fp16'"):
        make_policy(precision="fp16")


def test_a_runs_record_tells_cpus_of_one_brand_apart_by_family_model_and_bf16():
    zen3 = "processor\t: 0\nmodel name\t: AMD EPYC\ncpu family\t: 25\nmodel\t\t: 1\nflags\t\t: fpu avx2\n"
    zen4 = zen3.replace("model\t\t: 1", "model\t\t: 17").replace("avx2", "avx2 avx512f avx512_bf16")
    assert cpu_description(zen3) == "AMD EPYC, family 25 model 1, no native bf16"
    assert cpu_description(zen4) == "AMD EPYC, family 25 model 17, native bf16"
    assert cpu_description(zen3 + zen3.replace("processor\t: 0", "processor\t: 1")) == cpu_description(zen3)
    assert cpu_description(XEON_AMX_FLAGS).endswith(", native bf16")  # no model lines: the machine's arch


@pytest.mark.parametrize("method", ["concat", "separated_q"])
def test_bf16_losses_and_gradients_agree_with_fp32_on_a_batch(method):
    policy = make_policy(method)
    batch = transitions(256, seed=1)
    dtypes = {}

    def record(name):  # the dtype a layer's matmul ran in, first call of a forward
        return lambda module, inputs, output: dtypes.setdefault(name, output.dtype) and None

    policy.critic.first.register_forward_hook(record("hidden"))
    policy.critic.out.register_forward_hook(record("output"))
    policy.config.precision = "fp32"
    loss32, grads32 = loss_and_gradients(policy, batch)
    assert dtypes == {"hidden": torch.float32, "output": torch.float32}
    dtypes.clear()
    policy.config.precision = "bf16"
    loss16, grads16 = loss_and_gradients(policy, batch)
    assert dtypes == {"hidden": torch.bfloat16, "output": torch.float32}  # output layers stay fp32
    assert loss16.dtype == torch.float32 and all(p.dtype == torch.float32 for p in policy.parameters())
    assert loss16 != loss32  # bf16 did run
    torch.testing.assert_close(loss16, loss32, rtol=1e-2, atol=0)
    for name, g32 in grads32.items():
        g16 = grads16[name]
        assert torch.nn.functional.cosine_similarity(g16, g32, dim=0) > 0.99, name
        assert abs(g16.norm() / g32.norm() - 1) < 0.03, name


def test_fp32_overrides_an_outer_autocast():
    """lerobot-train with use_amp wraps forward in accelerate's autocast: precision fp32 still is fp32."""
    policy = make_policy()
    batch = transitions(64, seed=2)
    policy.config.precision = "fp32"
    plain, _ = policy.forward(batch)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        wrapped, _ = policy.forward(batch)
    assert torch.equal(plain, wrapped)


def test_training_in_bf16_learns_like_fp32():
    """The same 150 updates (same start, same batches) in both precisions: every loss falls,
    and by the same amount within a few percent (16x16 encoders' 80-number latents, for speed)."""
    data = transitions(2048, seed=3, latent_dim=80)
    curves = {}
    for precision in ("fp32", "bf16"):
        policy = make_policy(precision=precision, image_size=16)
        optimizer = policy.config.get_optimizer_preset().build(policy.get_optim_params())
        g = torch.Generator().manual_seed(0)
        losses = []
        for _ in range(150):
            rows = torch.randint(len(data[STATE]), (128,), generator=g)
            loss, info = policy.forward({k: v[rows] for k, v in data.items()})
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            policy.update()
            losses.append([info["value_loss"], info["critic_loss"], info["actor_loss"]])
        curves[precision] = torch.tensor(losses)
    for precision, curve in curves.items():
        first, last = curve[:10].mean(0), curve[-20:].mean(0)
        assert torch.all(last < 0.5 * first), (precision, first, last)  # value, critic and actor losses fell
    torch.testing.assert_close(curves["bf16"][-20:].mean(0), curves["fp32"][-20:].mean(0), rtol=0.05, atol=0.01)
