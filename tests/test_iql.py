"""The IQL building blocks of MURM (paper eq. 4-11)."""

import copy

import pytest
import torch

from lerobot_murm.policy.iql import (
    DoubleQ,
    GaussianPolicy,
    advantage_weights,
    camera_keep_mask,
    expectile_loss,
    polyak_update,
    sparse_reward,
)


def test_expectile_loss_weighs_positive_errors_by_tau():
    diff = torch.tensor([2.0, -2.0])
    assert expectile_loss(diff[:1], 0.9).item() == pytest.approx(0.9 * 4)
    assert expectile_loss(diff[1:], 0.9).item() == pytest.approx(0.1 * 4)
    assert expectile_loss(diff, 0.5).item() == pytest.approx(0.5 * 4)


def test_expectile_regression_converges_to_the_expectile():
    samples = torch.randn(20000, generator=torch.Generator().manual_seed(0))
    v = torch.zeros(1, requires_grad=True)
    optimizer = torch.optim.Adam([v], lr=0.05)
    for _ in range(400):
        optimizer.zero_grad()
        expectile_loss(samples - v, 0.9).backward()
        optimizer.step()
    assert v.item() > samples.quantile(0.75).item()  # the 0.9-expectile of N(0,1) is ~1.28


def test_advantage_weights_are_exponential_and_clipped():
    advantage = torch.tensor([-1.0, 0.0, 0.1, 5.0], requires_grad=True)
    weights = advantage_weights(advantage, beta=10.0, max_weight=100.0)
    expected = torch.tensor([torch.exp(torch.tensor(-10.0)), 1.0, torch.e, 100.0])
    torch.testing.assert_close(weights, expected)
    assert not weights.requires_grad


def test_polyak_update_moves_the_target_by_tau():
    source, target = torch.nn.Linear(2, 1), torch.nn.Linear(2, 1)
    before = copy.deepcopy(target)
    polyak_update(target, source, tau=0.25)
    for t, s, b in zip(target.parameters(), source.parameters(), before.parameters(), strict=True):
        torch.testing.assert_close(t, 0.75 * b + 0.25 * s)


def test_sparse_reward_counts_the_cameras_within_their_epsilon():
    z = torch.zeros(3, 2, 4)
    goal = torch.zeros(3, 2, 4)
    goal[1, 0, 0] = 1.5  # camera 0 off by 2.25 squared distance
    goal[2, :, 0] = 3.0  # both off by 9
    reward = sparse_reward(z, goal, epsilons=torch.tensor([2.0, 10.0]))
    assert reward.tolist() == [0.0, -1.0, -1.0]  # camera 1's epsilon 10 still counts 9 as reached
    assert sparse_reward(z, goal, torch.tensor([2.0, 2.0])).tolist() == [0.0, -1.0, -2.0]


def test_camera_dropout_drops_each_camera_at_rate_p_and_never_all():
    keep = camera_keep_mask(200_000, 2, p=0.5, generator=torch.Generator().manual_seed(0))
    assert keep.any(dim=1).all()
    # with the all-dropped rows restored, each camera is dropped with probability p - p^2 = 0.25
    assert (~keep).float().mean(0).sub(0.25).abs().max() < 0.01
    keep3 = camera_keep_mask(200_000, 3, p=0.1, generator=torch.Generator().manual_seed(1))
    assert (~keep3).float().mean(0).sub(0.1 - 0.001).abs().max() < 0.01
    assert camera_keep_mask(10, 1, p=0.9).all()  # one camera is never dropped


def _head(q: DoubleQ, which: int, group: int, x: torch.Tensor) -> torch.Tensor:
    """Q head `group` of set `which`, computed by hand from the ensemble's weights."""
    columns = slice(which * q.hidden, (which + 1) * q.hidden)
    h = x @ q.first.weight[group, :, columns] + q.first.bias[group, 0, columns]
    head = which * q.groups + group
    for layer in q.body:
        h = torch.relu(h) @ layer.weight[head] + layer.bias[head, 0]
    return (torch.relu(h) @ q.out.weight[head] + q.out.bias[head, 0]).squeeze(-1)


def test_separated_q_averages_one_head_per_camera():
    torch.manual_seed(0)
    q = DoubleQ(groups=2, group_dim=3, action_dim=4, hidden=8, layers=2)
    state, action = torch.randn(5, 2, 3), torch.randn(5, 4)
    q1, q2 = q(state, action)
    for which, values in ((0, q1), (1, q2)):
        heads = [_head(q, which, k, torch.cat([state[:, k], action], -1)) for k in range(2)]
        torch.testing.assert_close(values, (heads[0] + heads[1]) / 2)
    assert q2.shape == (5,) and not torch.allclose(q1, q2)
    # camera 1's input does not reach camera 0's heads
    other = state.clone()
    other[:, 1] += 1.0
    torch.testing.assert_close(
        _head(q, 0, 0, torch.cat([other[:, 0], action], -1)), _head(q, 0, 0, torch.cat([state[:, 0], action], -1))
    )


def test_double_q_on_the_whole_state_has_two_independent_heads():
    torch.manual_seed(0)
    q = DoubleQ(groups=1, group_dim=6, action_dim=4, hidden=8, layers=2)
    state, action = torch.randn(5, 1, 6), torch.randn(5, 4)
    q1, q2 = q(state, action)
    x = torch.cat([state[:, 0], action], -1)
    torch.testing.assert_close(q1, _head(q, 0, 0, x))
    torch.testing.assert_close(q2, _head(q, 1, 0, x))


def test_networks_have_the_paper_widths_and_depths():
    q = DoubleQ(groups=1, group_dim=1440, action_dim=4, hidden=128, layers=2)
    shapes = [tuple(q.first.weight.shape)] + [tuple(m.weight.shape) for m in (*q.body, q.out)]
    assert shapes == [(1, 1444, 2 * 128), (2, 128, 128), (2, 128, 1)]  # two heads of 1444 -> 128 -> 128 -> 1
    policy = GaussianPolicy(1440, 4, hidden=128, layers=4, log_std_min=-2.0, log_std_max=-1.0)
    assert [m.out_features for m in policy.mean if isinstance(m, torch.nn.Linear)] == [128] * 4 + [4]
    actions = policy.act(torch.randn(7, 1440), deterministic=False)
    assert actions.shape == (7, 4) and actions.abs().max() <= 1.0
    std = policy.distribution(torch.randn(2, 1440)).stddev
    assert torch.all(std >= torch.exp(torch.tensor(-2.0)) - 1e-6)
    assert torch.all(std <= torch.exp(torch.tensor(-1.0)) + 1e-6)
