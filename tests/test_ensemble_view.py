"""SOUPPolicy.ensemble_view: the candidates, V, W, the chosen head and the critic heads' disagreement, as predict sees them."""

import json

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from scripts import load_script

from sb3_soup import SOUP, EnsembleView

TINY = dict(net_arch=dict(pi_body=[8], pi_head=[8], qf_body=[8, 8], qf_head=[8]))
SMALL = dict(n_heads=3, learning_starts=20, batch_size=16, buffer_size=500, seed=0, device="cpu", policy_kwargs=TINY)
MODELS = {
    "ddpg": dict(preset="ddpg"),
    "ma_bddpg": dict(preset="ma_bddpg"),
    "multi_ddpg": dict(preset="multi_ddpg"),
    "soup": dict(preset="soup"),
    "fixed": dict(confidence="fixed"),
    "ucb": dict(confidence="ucb", confidence_kwargs=dict(ucb_lambda=2.0)),
}


@pytest.fixture(scope="module", params=sorted(MODELS))
def trained(request) -> SOUP:
    model = SOUP("MlpPolicy", "Pendulum-v1", **SMALL, **MODELS[request.param])
    return model.learn(60)  # trained a little, so that the heads differ


def observations(model: SOUP, n: int = 7) -> np.ndarray:
    model.observation_space.seed(1)
    return np.stack([model.observation_space.sample() for _ in range(n)])  # (B, 3)


def test_view_is_what_predict_acts_on(trained):
    policy, obs = trained.policy, observations(trained)
    view = policy.ensemble_view(obs)
    assert isinstance(view, EnsembleView) and all(isinstance(field, np.ndarray) for field in view)
    n_actor, n_critic = policy.n_actor_heads, policy.n_critic_heads
    assert view.actions.shape == (7, 1) and view.candidates.shape == (7, n_actor, 1)
    assert view.q_matrix.shape == view.weights.shape == (7, n_critic, n_actor)
    assert view.e_q.shape == (7, n_actor) and view.chosen.shape == view.q_mean.shape == view.q_spread.shape == (7,)
    np.testing.assert_array_equal(view.actions, trained.predict(obs, deterministic=True)[0])
    np.testing.assert_array_equal(view.actions, view.candidates[np.arange(7), view.chosen])
    # each field is what its definition says, recomputed from the networks
    with th.no_grad():
        obs_tensor = th.as_tensor(obs)
        candidates = policy.actor(obs_tensor)  # (Ka, B, A) in [-1, 1]
        rows = [th.stack([policy.critic(obs_tensor, a, head=i)[:, 0] for a in candidates], 1) for i in range(n_critic)]
        q = th.stack(rows, 1)  # (B, Kc, Ka), one head and one candidate at a time
    np.testing.assert_allclose(view.candidates, policy.unscale_action(candidates.transpose(0, 1).numpy()), rtol=1e-6)
    np.testing.assert_allclose(view.q_matrix, q.numpy(), rtol=1e-5, atol=1e-6)  # V[b, i, k] = Q_i(s_b, a_b^k)
    np.testing.assert_allclose(view.e_q, (view.weights * view.q_matrix).sum(1), rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(view.chosen, view.e_q.argmax(1))
    chosen_q = view.q_matrix[np.arange(7), :, view.chosen]  # (B, Kc)
    np.testing.assert_allclose(view.q_mean, chosen_q.mean(1), rtol=1e-5, atol=1e-6)
    spread = chosen_q.std(1, ddof=1) if n_critic > 1 else np.zeros(7)
    np.testing.assert_allclose(view.q_spread, spread, rtol=1e-4, atol=1e-6)
    if n_critic > 1 and n_actor > 1:
        assert (view.q_spread > 0).all() and len(np.unique(view.candidates[0, :, 0])) == n_actor


def test_view_changes_nothing(trained):
    """predict returns the same (deterministic and noisy) actions with or without a view between, from the same state."""
    policy, obs = trained.policy, observations(trained)
    state = {key: value.clone() for key, value in policy.state_dict().items()}
    th.manual_seed(3)
    plain = [trained.predict(obs, deterministic=False)[0] for _ in range(2)]
    th.manual_seed(3)
    first = trained.predict(obs, deterministic=False)[0]
    policy.ensemble_view(obs)
    policy.ensemble_view(obs, explore=True)
    second = trained.predict(obs, deterministic=False)[0]
    np.testing.assert_array_equal(first, plain[0])
    np.testing.assert_array_equal(second, plain[1])  # the view drew no random number
    # predict adds no noise (as TD3's: the exploration noise is the algorithm's); UCB explores with its bonus
    np.testing.assert_array_equal(plain[0], plain[1])
    np.testing.assert_array_equal(trained.predict(obs, deterministic=True)[0], policy.ensemble_view(obs).actions)
    assert all(th.equal(value, state[key]) for key, value in policy.state_dict().items())


def test_unbatched_observation_drops_the_batch_dimension(trained):
    obs = observations(trained)
    single, batch = trained.policy.ensemble_view(obs[2]), trained.policy.ensemble_view(obs)
    assert single.actions.shape == (1,) and single.chosen.shape == () and single.q_matrix.ndim == 2
    for one, many in zip(single, batch):
        np.testing.assert_allclose(one, many[2], rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(single.actions, trained.predict(obs[2], deterministic=True)[0])


def test_explore_view_shows_the_ucb_bonus():
    """With explore=True the weights are the strategy's exploration weights: UCB's mean + lambda * std of the heads."""
    model = SOUP("MlpPolicy", "Pendulum-v1", **SMALL, confidence="ucb", confidence_kwargs=dict(ucb_lambda=2.0)).learn(60)
    obs = observations(model)
    greedy, optimistic = model.policy.ensemble_view(obs), model.policy.ensemble_view(obs, explore=True)
    np.testing.assert_array_equal(greedy.q_matrix, optimistic.q_matrix)
    np.testing.assert_allclose(greedy.e_q, greedy.q_matrix.mean(1), rtol=1e-5, atol=1e-6)  # the mean of the heads
    bonus = greedy.q_matrix.mean(1) + 2.0 * greedy.q_matrix.std(1)
    np.testing.assert_allclose(optimistic.e_q, bonus, rtol=1e-4, atol=1e-5)
    np.testing.assert_array_equal(optimistic.chosen, optimistic.e_q.argmax(1))


def test_dict_observations():
    env_space = spaces.Dict({"a": spaces.Box(-1, 1, (2,)), "b": spaces.Box(-1, 1, (3,))})

    from test_bad_input import ToyEnv  # 20-step episodes of random observations

    model = SOUP("MultiInputPolicy", ToyEnv(env_space, spaces.Box(-3, 3, (2,))), **SMALL)
    env_space.seed(0)
    batch = {key: np.stack([env_space.sample()[key] for _ in range(4)]) for key in env_space.spaces}
    view = model.policy.ensemble_view(batch)
    assert view.q_matrix.shape == (4, 3, 3) and view.candidates.shape == (4, 3, 2)
    np.testing.assert_array_equal(view.actions, model.predict(batch, deterministic=True)[0])
    with th.no_grad():
        scaled = model.policy.actor(model.policy.obs_to_tensor(batch)[0]).transpose(0, 1).numpy()  # (B, Ka, A) in [-1, 1]
    np.testing.assert_allclose(view.candidates, 3 * scaled, rtol=1e-6, atol=1e-6)  # in the env's bounds [-3, 3]


def test_example_runs(capsys):
    """examples/ensemble_uncertainty.py, on a tiny budget: it prints the view of visited and unseen states."""
    example = load_script("examples/ensemble_uncertainty.py")
    seen, unseen = example.main(timesteps=150, n_heads=2, n_states=2)
    out = capsys.readouterr().out
    assert "States the policy visits:" in out and "never saw" in out and "mean Q spread" in out
    assert seen > 0 and unseen > 0


def test_heads_example(tmp_path):
    """examples/ensemble_heads.py: the E-action's returns are evaluate_policy's of the model, on the same episodes; one
    entry per actor head; the executed candidates' shares add up to 1."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy

    example = load_script("examples/ensemble_heads.py")
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, learning_starts=50, seed=0)
    model.learn(150)
    model.save(tmp_path / "model.zip")
    result = example.main(
        [str(tmp_path / "model.zip"), "--env", "Pendulum-v1", "--episodes", "2", "--json", str(tmp_path / "h.json")]
    )
    expected, _ = evaluate_policy(
        model, make_vec_env("Pendulum-v1", n_envs=1, seed=1000), n_eval_episodes=2, return_episode_rewards=True
    )
    np.testing.assert_allclose(result["e_action"]["returns"], expected, rtol=1e-5)
    assert len(result["heads"]) == 3 and all(len(head["returns"]) == 2 for head in result["heads"])
    assert sum(result["chosen_fraction"]) == pytest.approx(1.0)
    assert json.loads((tmp_path / "h.json").read_text())["e_action"] == result["e_action"]
