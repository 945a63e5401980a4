"""caviar.gym: Gymnasium and PettingZoo environments over a configuration, checked by the
libraries' own checkers, on a toy world (tests/gym_plugins.py) and on the beam-selection
task with Sionna RT in the loop (few rays, few steps)."""

import json
import pathlib

import numpy as np
import pytest
from gymnasium import spaces
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test

import caviar
import caviar.gym
import configs
from caviar_plugins.beam_selection.gym_task import PAIRS, beam_selection_spec
from caviar_plugins.radio.link_budget import LinkBudget

ROOT = pathlib.Path(__file__).resolve().parent.parent
BEAM_GYM = ROOT / "blueprints" / "beam-gym"
# (one Dr.Jit thread: the solver's parallel sums differ in their last bits from run to run with
# several, and check_env steps twice from one seed and wants the same rewards exactly)
FEW_RAYS = {"modules.comm.params.raytracing.samples_per_src": 10000, "modules.comm.params.raytracing.threads": 1}

TOY = (configs.episode(0.1, ["world", "agent", "judge"], steps=5, seed=3)
       + configs.module("target", "world", "gym_plugins:Target")
       + configs.module("guesser", "agent", "gym_plugins:Guesser")
       + configs.module("judge", "judge", "gym_plugins:Judge"))


def toy_spec(topic: str = "toy.target") -> caviar.gym.AgentSpec:
    """Observe the target, publish a guess, earn minus the judge's error."""

    def observe(inbox):
        m = inbox.latest(topic)
        return np.array([m.data["value"] if m else 0.0], dtype=np.float32)

    return caviar.gym.AgentSpec(
        subscribe=(topic,), observation_space=spaces.Box(-1.0, 1.0, (1,), np.float32),
        action_space=spaces.Box(-1.0, 1.0, (1,), np.float32), observe=observe,
        act=lambda a: [("toy.guess", {"value": float(a[0])})],
        reward=lambda messages: -sum(m.data["error"] for m in messages if m.topic == "toy.score"),
        info=lambda messages: {"scores": sum(m.topic == "toy.score" for m in messages)})


@pytest.fixture
def toy(tmp_path, monkeypatch):
    """The toy configuration; its plugins importable here and in NATS workers."""
    monkeypatch.setenv("PYTHONPATH", str(ROOT / "tests"))
    path = tmp_path / "toy.toml"
    path.write_text(TOY)
    return path


def episode(env, seed, actions):
    """(observations, rewards, terminated, truncated) of an episode with these actions."""
    obs, _ = env.reset(seed=seed)
    seen, rewards = [obs], []
    for a in actions:
        obs, r, terminated, truncated, _ = env.step(a)
        seen.append(obs)
        rewards.append(r)
        if terminated or truncated:
            break
    return seen, rewards, terminated, truncated


def test_the_toy_environment_passes_gymnasiums_checker_and_rewards_the_step_of_the_action(toy, tmp_path):
    env = caviar.gym.make(toy, "guesser", toy_spec(), out=tmp_path / "runs")
    try:
        check_env(env, skip_render_check=True)
        obs, _ = env.reset(seed=11)
        # Guessing the observed target exactly: the judge, later in the same step, scores 0.
        obs, reward, terminated, truncated, info = env.step(obs)
        assert reward == pytest.approx(0.0, abs=1e-6) and info == {"scores": 1}
        # Guessing 0.5 against target x costs |x - 0.5| (the judge's error, recomputed here).
        target = float(obs[0])
        _, reward, *_ = env.step(np.array([0.5], np.float32))
        assert reward == pytest.approx(-abs(target - 0.5), abs=1e-6)
    finally:
        env.close()


def test_same_seed_same_episode_other_seed_other_episode(toy, tmp_path):
    env = caviar.gym.make(toy, "guesser", toy_spec(), out=tmp_path / "runs")
    actions = [np.array([v], np.float32) for v in (0.1, -0.3, 0.7, 0.0, 0.2)]
    try:
        a, b, c = (episode(env, seed, actions) for seed in (5, 5, 6))
    finally:
        env.close()
    assert np.array_equal(np.concatenate(a[0]), np.concatenate(b[0])) and a[1] == b[1]
    assert not np.array_equal(np.concatenate(a[0]), np.concatenate(c[0]))
    # Every reset is a run of its own, with the seed it was given.
    runs = sorted((tmp_path / "runs").iterdir())
    assert [caviar.load_run(r).status["seed"] for r in runs] == [5, 5, 6]


def test_terminated_when_a_module_ends_the_episode_truncated_at_the_step_limit(toy, tmp_path):
    zero = np.zeros(1, np.float32)
    env = caviar.gym.make(toy, "guesser", toy_spec(), out=tmp_path / "a",
                          overrides={"modules.target.params.end_at": 2})
    try:
        _, rewards, terminated, truncated = episode(env, 1, [zero] * 10)
        assert (len(rewards), terminated, truncated) == (3, True, False)  # steps 0, 1, 2; ended by `target`
        assert caviar.load_run(env.run_dir).status["end_reason"] == "module"
    finally:
        env.close()
    env = caviar.gym.make(toy, "guesser", toy_spec(), out=tmp_path / "b")  # episode.steps = 5
    try:
        _, rewards, terminated, truncated = episode(env, 1, [zero] * 10)
        assert (len(rewards), terminated, truncated) == (5, False, True)
        assert caviar.load_run(env.run_dir).status["end_reason"] == "steps"
    finally:
        env.close()
    env = caviar.gym.make(toy, "guesser", toy_spec(), out=tmp_path / "c", max_steps=2)  # the agent's limit
    try:
        _, rewards, terminated, truncated = episode(env, 1, [zero] * 10)
        assert (len(rewards), terminated, truncated) == (2, False, True)
        assert rewards[-1] < 0  # the last action was judged before the episode was closed
        assert caviar.load_run(env.run_dir).status["end_reason"] == "closed"
    finally:
        env.close()


def test_close_ends_the_episode_and_run_json_says_so(toy, tmp_path):
    env = caviar.gym.make(toy, "guesser", toy_spec(), out=tmp_path / "runs")
    env.reset(seed=2)
    env.step(np.zeros(1, np.float32))
    env.close()
    status = json.loads((env.run_dir / "run.json").read_text())
    assert status["status"] == "completed" and status["end_reason"] == "closed"
    assert status["steps_done"] == 2  # the step in progress when the agent was waiting finished first
    env.close()  # twice is harmless


def test_a_second_environment_on_the_same_out_goes_on_numbering_its_episodes(toy, tmp_path):
    """The same script run twice with one ``out``: its episodes follow the earlier ones
    (it stopped with "episode-0001 exists and is not empty")."""
    for seed in (3, 4):
        env = caviar.gym.make(toy, "guesser", toy_spec(), out=tmp_path / "runs")
        try:
            env.reset(seed=seed)
            env.step(np.zeros(1, np.float32))
        finally:
            env.close()
    runs = sorted((tmp_path / "runs").iterdir())
    assert [r.name for r in runs] == ["episode-0001", "episode-0002"]
    assert [caviar.load_run(r).status["seed"] for r in runs] == [3, 4]


def test_bad_input_is_named(toy, tmp_path):
    with pytest.raises(caviar.ConfigError, match=r"agent 'nope' is not a module .*modules: target, guesser, judge"):
        caviar.gym.make(toy, "nope", toy_spec())
    with pytest.raises(caviar.ConfigError, match=r"agent module 'guesser' observes 'toy.nothing', which no module "):
        caviar.gym.make(toy, "guesser", toy_spec("toy.nothing"))
    with pytest.raises(caviar.ConfigError, match="cannot read the configuration"):
        caviar.gym.make(tmp_path / "missing.toml", "guesser", toy_spec())
    env = caviar.gym.make(toy, "guesser", toy_spec(), out=tmp_path / "runs")
    try:
        with pytest.raises(RuntimeError, match="call reset"):
            env.step(np.zeros(1, np.float32))
        env.reset(seed=1)
        with pytest.raises(ValueError, match=r"action array\(\[3\.\].*\) of agent 'guesser' .* outside its action "):
            env.step(np.array([3.0], np.float32))
        env.step(np.zeros(1, np.float32))  # the episode goes on after a refused action
    finally:
        env.close()


def test_a_failing_module_raises_run_error_naming_it(toy, tmp_path):
    env = caviar.gym.make(toy, "guesser", toy_spec(), out=tmp_path / "runs",
                          overrides={"modules.judge.params.fail_on": 0.5})
    try:
        env.reset(seed=1)
        env.step(np.zeros(1, np.float32))
        with pytest.raises(caviar.RunError, match="the judge refuses the guess 0.5") as e:
            env.step(np.array([0.5], np.float32))
        assert e.value.module == "judge" and e.value.step == 1
        assert caviar.load_run(env.run_dir).status["status"] == "failed"
        env.reset(seed=1)  # a new episode after the failure
        env.step(np.zeros(1, np.float32))
    finally:
        env.close()


def test_over_nats_the_same_episode_as_in_process(toy, tmp_path):
    """The other modules (and the agent module's proxy) in NATS worker processes, with the
    nats-server the run starts: the same observations and rewards as in-process."""
    actions = [np.array([v], np.float32) for v in (0.1, -0.3, 0.7, 0.0, 0.2)]
    env = caviar.gym.make(toy, "guesser", toy_spec(), out=tmp_path / "inproc")
    try:
        local = episode(env, 4, actions)
    finally:
        env.close()
    env = caviar.gym.make(toy, "guesser", toy_spec(), out=tmp_path / "nats", overrides={"transport.kind": "nats"})
    try:
        remote = episode(env, 4, actions)
        workers = sorted(p.name for p in (env.run_dir / "workers").iterdir())
    finally:
        env.close()
    assert np.array_equal(np.concatenate(local[0]), np.concatenate(remote[0]))
    assert local[1:] == remote[1:]
    assert any(w.startswith("guesser") for w in workers) and any(w.startswith("judge") for w in workers)


def test_beam_selection_env_passes_check_env_and_its_reward_is_the_throughput_ratio(tmp_path):
    """Sionna RT in the loop (1e4 rays): the reward is the chosen pair's throughput over the
    best pair's, recomputed here from the recorded gains of all pairs and the link budget."""
    spec = beam_selection_spec("uav1", previous_gains=True)
    env = caviar.gym.make(BEAM_GYM / "config.toml", "beams", spec, out=tmp_path / "runs",
                          overrides={**FEW_RAYS, "episode.steps": 3})
    try:
        check_env(env, skip_render_check=True)
        obs, _ = env.reset(seed=3)
        assert not obs["previous_gains"].any()  # no sweep before the first step
        chosen, rewards, infos = [7, 200, 64], [], []
        for pair in chosen:
            obs, reward, terminated, truncated, info = env.step(pair)
            rewards.append(reward)
            infos.append(info)
        assert (terminated, truncated) == (False, True)
        log = caviar.load_run(env.run_dir)
    finally:
        env.close()
    gains = [np.asarray(m.data, float).ravel() for m in log.decoded("communications.beam_gains.uav1")]
    assert len(gains) == 3 and gains[0].size == PAIRS
    budget = LinkBudget(bandwidth_hz=40e6, tx_power_w=0.5, interference_dbw=-130.0)  # sionna-link's defaults
    for g, pair, reward, info in zip(gains, chosen, rewards, infos, strict=True):
        assert info["pair"] == pair and info["best_pair"] == int(np.argmax(g))
        assert reward == pytest.approx(budget.throughput_mbps(g[pair]) / budget.throughput_mbps(g.max()), rel=1e-5)
        assert 0.0 <= reward <= 1.0 and info["top1"] == (pair == int(np.argmax(g)))
    # An observation carries the previous step's sweep, divided by its maximum (the episode's
    # last observation is the agent module's last inbox: that of step 2, with the sweep of step 1).
    assert np.allclose(obs["previous_gains"], gains[1] / gains[1].max(), rtol=1e-5)


def test_two_uavs_pass_pettingzoos_parallel_api_test_and_repeat_with_a_seed(tmp_path):
    specs = {ue: beam_selection_spec(ue) for ue in ("uav1", "uav2")}
    env = caviar.gym.make_parallel(BEAM_GYM / "two-uavs.toml", "beams", specs, out=tmp_path / "runs",
                                   overrides={**FEW_RAYS, "episode.steps": 3})
    try:
        parallel_api_test(env, num_cycles=10)
        runs = []
        for _ in range(2):
            obs, infos = env.reset(seed=9)
            assert set(obs) == {"uav1", "uav2"} and not np.allclose(obs["uav1"]["position"], obs["uav2"]["position"])
            steps = []
            while env.agents:
                obs, rewards, terminated, truncated, infos = env.step({"uav1": 5, "uav2": 130})
                steps.append((obs, rewards, infos))
            runs.append(steps)
        assert terminated == {"uav1": False, "uav2": False} and truncated == {"uav1": True, "uav2": True}
        for (o1, r1, i1), (o2, r2, i2) in zip(*runs, strict=True):
            # Flights and pairs repeat exactly; the gains traced for two receivers in one solve with
            # 1e4 rays do not quite (weak NLOS paths, Dr.Jit's parallel sums on the CPU), hence the tolerance.
            assert all(np.array_equal(o1[a]["position"], o2[a]["position"]) for a in o1)
            assert r1 == pytest.approx(r2, rel=0.1, abs=1e-4)
            assert [(i["pair"], i["best_pair"], i["los"]) for i in i1.values()] == \
                [(i["pair"], i["best_pair"], i["los"]) for i in i2.values()]
        assert {i["pair"] for i in i1.values()} == {5, 130}  # each UAV's link used its agent's pair
    finally:
        env.close()


def test_a_tiny_learning_baseline_beats_random_choice(tmp_path):
    """Two training flights of 15 steps, 12 steps of the held-out flight, 1e4 rays: the agent
    trained in the environment already does better than random; the oracle is the best."""
    from caviar_plugins.tools.baselines import gym_baseline

    report = gym_baseline.main(["--episodes", "2", "--steps", "15", "--test-steps", "12", "--rays", "10000",
                                "--runs", str(tmp_path / "runs"), "--out", str(tmp_path / "out"), "--quiet"])
    table = report["table"]
    agent, random, oracle = table["trained agent (SweepBandit)"], table["random"], table["oracle"]
    assert report["train_samples"] == 30 and report["test_steps"] == 12
    assert agent["mean_reward"] > random["mean_reward"] + 0.1 and agent["top1_pct"] > random["top1_pct"]
    assert oracle["top1_pct"] == 100.0 and oracle["mean_reward"] == 1.0
    assert all(s["throughput_mbps"] <= oracle["throughput_mbps"] + 1e-9 for s in table.values())
    written = json.loads((tmp_path / "out" / "gym-baseline.json").read_text())
    assert written["table"] == table and (tmp_path / "out" / "gym-baseline.png").stat().st_size > 10_000
    assert "| trained agent (SweepBandit) |" in (tmp_path / "out" / "gym-baseline.md").read_text()
