"""The authors' learners (numpy transcriptions) against torch autograd and on toy tasks."""

import numpy as np
import pytest
import torch

from tamrm_experiments.learners import MLP, ActorCritic, Adam, RMSPropTF1, TutorialDQN


def _torch_mlp(net: MLP):
    ps = [torch.tensor(p, requires_grad=True) for p in net.params()]

    def f(x):
        return torch.relu(x @ ps[0] + ps[1]) @ ps[2] + ps[3]

    return ps, f


def test_mlp_backward_matches_autograd():
    rng = np.random.default_rng(0)
    net = MLP.init(rng, 4, 20, 3, 0.3)
    x = rng.normal(size=(7, 4))
    g_out = rng.normal(size=(7, 3))
    out, h = net.forward(x)
    grads = net.backward(x, h, g_out)
    ps, f = _torch_mlp(net)
    y = f(torch.tensor(x))
    assert np.allclose(y.detach().numpy(), out)
    (y * torch.tensor(g_out)).sum().backward()
    for g, p in zip(grads, ps, strict=True):
        assert np.allclose(g, p.grad.numpy())


def test_adam_matches_torch():
    rng = np.random.default_rng(1)
    w = rng.normal(size=(3, 2))
    tw = torch.tensor(w.copy(), requires_grad=True)
    opt = Adam([w], lr=0.01)
    topt = torch.optim.Adam([tw], lr=0.01, eps=1e-8)
    for _ in range(5):
        g = rng.normal(size=(3, 2))
        opt.step([g])
        tw.grad = torch.tensor(g)
        topt.step()
    # TensorFlow's Adam folds the bias correction into the rate: equal up to epsilon.
    assert np.allclose(w, tw.detach().numpy(), atol=1e-6)


def test_rmsprop_tf1_accumulator_starts_at_one():
    w = np.zeros(1)
    opt = RMSPropTF1([w], lr=0.1)
    opt.step([np.array([2.0])])
    # ms = 0.9 * 1 + 0.1 * 4 = 1.3
    assert w[0] == pytest.approx(-0.1 * 2.0 / np.sqrt(1.3))


def test_actor_critic_step_matches_autograd():
    rng = np.random.default_rng(2)
    ac = ActorCritic(4, 2, rng)
    ps_a, fa = _torch_mlp(ac.actor)
    ps_c, fc = _torch_mlp(ac.critic)
    s, s2 = rng.normal(size=4), rng.normal(size=4)
    a, r = 1, 0.7
    ts, ts2 = torch.tensor(s[None]), torch.tensor(s2[None])
    v_next = fc(ts2).detach()
    td_t = r + 0.9 * v_next - fc(ts)
    (td_t**2).sum().backward()
    logp = torch.log(torch.softmax(fa(ts), -1)[0, a] + 1e-8)
    (-(logp * td_t.detach()).sum()).backward()
    grads_c = [p.grad.numpy().copy() for p in ps_c]
    grads_a = [p.grad.numpy().copy() for p in ps_a]
    before_c = [p.copy() for p in ac.critic.params()]
    before_a = [p.copy() for p in ac.actor.params()]
    td = ac.learn(s, a, r, s2)
    assert td == pytest.approx(float(td_t.detach()))
    # Adam's first step moves each parameter by lr * sign(g) (where g != 0).
    for b, p, g in zip(before_c, ac.critic.params(), grads_c, strict=True):
        assert np.allclose((b - p)[g != 0], 1e-2 * np.sign(g[g != 0]), rtol=1e-3)
    for b, p, g in zip(before_a, ac.actor.params(), grads_a, strict=True):
        nz = np.abs(g) > 1e-12
        assert np.allclose((b - p)[nz], 1e-3 * np.sign(g[nz]), rtol=1e-3)


def test_actor_critic_learns_a_bandit():
    rng = np.random.default_rng(3)
    ac = ActorCritic(1, 2, rng, gamma=0.0)
    s = np.ones(1)
    for _ in range(800):
        a = ac.act(s)
        ac.learn(s, a, 1.0 if a == 1 else 0.0, s)
    assert ac.probs(s)[1] > 0.9


def test_dqn_schedule_and_target():
    rng = np.random.default_rng(4)
    dqn = TutorialDQN(2, 3, rng, memory_size=100, replace_target_iter=5)
    s = np.zeros(2)
    for i in range(101):
        dqn.observe(s, i % 3, -1.0, s)
    assert dqn.learn_steps == 0 and dqn.epsilon == 1.0  # learns only after 100 steps
    dqn.observe(s, 0, -1.0, s)
    assert dqn.learn_steps == 1
    assert dqn.greedy == pytest.approx(5e-5)
    for _ in range(4):
        dqn.observe(s, 0, -1.0, s)
    assert dqn.learn_steps == 5
    before = dqn.q.w2.copy()
    assert not np.allclose(dqn.target.w2, before)  # copied before learn step 0 only
    dqn.observe(s, 0, -1.0, s)
    assert np.allclose(dqn.target.w2, before)  # and again before learn step 5


def test_dqn_learns_a_one_step_task():
    rng = np.random.default_rng(5)
    dqn = TutorialDQN(2, 2, rng, memory_size=200, gamma=0.0, greedy_increment=0.01)
    states = [np.array([1.0, 0.0]), np.array([0.0, 1.0])]
    for i in range(3000):
        s = states[i % 2]
        a = dqn.act(s)
        dqn.observe(s, a, 1.0 if a == i % 2 else 0.0, s)
    assert int(np.argmax(dqn.q_values(states[0]))) == 0
    assert int(np.argmax(dqn.q_values(states[1]))) == 1
