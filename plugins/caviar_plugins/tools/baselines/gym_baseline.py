"""A learning baseline in the beam-selection environment: an agent trained by playing the
``beams`` module of ``blueprints/beam-gym`` (Sionna RT in the loop), compared on a held-out
flight with random choice, the paper's decision tree and the oracle.

    python -m caviar_plugins.tools.baselines.gym_baseline                  # about 10 min on 2 cores
    python -m caviar_plugins.tools.baselines.gym_baseline --episodes 1 --steps 20 --test-steps 20 --rays 10000

The agent (:class:`SweepBandit`) is an ε-greedy contextual bandit: its observation is the
UAV position and the previous step's beam sweep (``beam_selection_spec(previous_gains=True)``);
it scores every pair with one gradient-boosted regression of a pair's normalised gain from
the pair's features in that context, and learns from the sweep of the step it acted in,
which the next observation brings (full feedback: the gains of all pairs, not only the
reward of its own choice). Training: one
episode per seed (a random-waypoint flight each). Evaluation: one episode of the test flight
(``test-flight.toml``, the SAR route, never flown in training), the agent greedy.

The other selectors are scored on the same steps of that episode, from its recorded sweeps
(the channel does not depend on the chosen pair): *random* (uniform pairs, seeded), *tree*
(the paper's: depth 15 on (x, y, z), fitted on the best pairs of the training episodes'
recordings), *previous* (the best pair of the previous step's sweep) and the *oracle* (the
best pair of the step). Throughput = B log2(1 + SNR) of the pair's gain (sionna-link's link
budget); the agent's, measured by the environment, must equal the one recomputed from the
sweeps (checked). Writes ``gym-baseline.{md,json,png}``.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time
from typing import Any

import numpy as np

import caviar
import caviar.gym
from caviar_plugins.beam_selection.decision_tree import MAX_DEPTH
from caviar_plugins.beam_selection.decision_tree import train as train_tree
from caviar_plugins.beam_selection.gym_task import PAIRS, beam_selection_spec
from caviar_plugins.radio.link_budget import LinkBudget
from caviar_plugins.schema import BEAM_GAINS, POSITIONS, per_ue, read_position

ROOT = pathlib.Path(__file__).resolve().parents[4]
BLUEPRINT = ROOT / "blueprints" / "beam-gym"
UE = "uav1"
AGENT_MODULE = "beams"


class SweepBandit:
    """ε-greedy contextual bandit over the beam pairs with a shared value model: a gradient-boosted
    regression predicts a pair's gain (divided by the step's best) from features of the pair in
    the context (its gain in the previous sweep, the best gain among its neighbouring beams,
    its rank, its Rx/Tx beam indices, the UAV position). The agent picks the pair of highest
    prediction, or a random one with probability ``epsilon`` while training, and refits every
    ``refit_every`` steps on all it has seen (256 samples a step: the sweep of the step it acted
    in gives every pair's gain)."""

    RX, TX_Y, TX_Z = 4, 8, 8
    """The codebooks: 4 Rx beams (2 × 2) and 64 Tx beams (8 × 8 Kronecker DFT, index p·8 + q)."""

    def __init__(self, epsilon: float = 0.1, refit_every: int = 25, seed: int = 0):
        self.epsilon, self.refit_every, self.seed = epsilon, refit_every, seed
        self.pairs = self.RX * self.TX_Y * self.TX_Z
        self.rng = np.random.default_rng(seed)
        self.x: list[np.ndarray] = []
        self.y: list[np.ndarray] = []
        self.model: Any = None
        r, t = np.divmod(np.arange(self.pairs), self.TX_Y * self.TX_Z)
        self._beams = np.stack([r, *np.divmod(t, self.TX_Z)], axis=1).astype(np.float64)

    def features(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """One row per pair: previous gain, its log, best neighbouring Tx beam, best other Rx
        beam, rank in the previous sweep, whether there was a sweep, beam indices, position."""
        g = np.asarray(obs["previous_gains"], dtype=np.float64)
        grid = g.reshape(self.RX, self.TX_Y, self.TX_Z)
        tx_near = np.max([np.roll(grid, s, axis=a) for s in (1, -1) for a in (1, 2)], axis=0).ravel()
        rx_near = np.max([np.roll(grid, s, axis=0) for s in range(1, self.RX)], axis=0).ravel()
        rank = np.empty(self.pairs)
        rank[np.argsort(-g, kind="stable")] = np.arange(self.pairs) / self.pairs
        swept = np.full(self.pairs, float(g.any()))
        position = np.broadcast_to(np.asarray(obs["position"], dtype=np.float64), (self.pairs, 3))
        return np.column_stack([g, np.log10(g + 1e-4), tx_near, rx_near, rank, swept, self._beams, position])

    def act(self, obs: dict[str, np.ndarray], explore: bool) -> int:
        if self.model is None or (explore and self.rng.random() < self.epsilon):
            return int(self.rng.integers(self.pairs))
        return int(np.argmax(self.model.predict(self.features(obs))))

    def learn(self, obs: dict[str, np.ndarray], next_obs: dict[str, np.ndarray]) -> None:
        """One transition: the sweep of the step acted in is ``next_obs["previous_gains"]``."""
        self.x.append(self.features(obs))
        self.y.append(np.asarray(next_obs["previous_gains"], dtype=np.float64))
        if len(self.x) % self.refit_every == 0:
            self.fit()

    def fit(self) -> None:
        from sklearn.ensemble import HistGradientBoostingRegressor

        self.model = HistGradientBoostingRegressor(max_iter=100, random_state=self.seed)
        self.model.fit(np.concatenate(self.x), np.concatenate(self.y))


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m caviar_plugins.tools.baselines.gym_baseline", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", type=pathlib.Path, default=BLUEPRINT / "config.toml", help="training flights")
    ap.add_argument("--test", type=pathlib.Path, default=BLUEPRINT / "test-flight.toml", help="held-out flight")
    ap.add_argument("--episodes", type=int, default=4, help="training episodes (one flight each)")
    ap.add_argument("--steps", type=int, default=150, help="steps of a training episode")
    ap.add_argument("--test-steps", type=int, default=150, help="steps of the test flight")
    ap.add_argument("--rays", type=int, default=100000, help="Sionna RT samples per source")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--runs", type=pathlib.Path, default=pathlib.Path("runs/gym-baseline"))
    ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path("docs/results"))
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    return ap.parse_args(argv)


def train(args: argparse.Namespace, agent: SweepBandit, progress) -> tuple[list[pathlib.Path], list[float]]:
    """Plays the training episodes; their run directories and the per-step top-1 hits."""
    env = caviar.gym.make(args.config, AGENT_MODULE, beam_selection_spec(UE, previous_gains=True),
                          overrides={"episode.steps": args.steps,
                                     "modules.comm.params.raytracing.samples_per_src": args.rays},
                          out=args.runs / "train")
    runs, hits = [], []
    try:
        for episode in range(args.episodes):
            obs, _ = env.reset(seed=args.seed + 1 + episode)
            done = False
            while not done:
                action = agent.act(obs, explore=True)
                next_obs, _, terminated, truncated, info = env.step(action)
                done = terminated or truncated
                if not done:  # the last observation brings no new sweep
                    agent.learn(obs, next_obs)
                hits.append(float(info.get("top1", False)))
                obs = next_obs
                progress.update(1)
                progress.set_postfix(episode=episode + 1, top1=f"{np.mean(hits[-50:]):.2f}")
            assert env.run_dir is not None
            runs.append(env.run_dir)
    finally:
        env.close()
    agent.fit()
    return runs, hits


def evaluate(args: argparse.Namespace, agent: SweepBandit, progress) -> tuple[pathlib.Path, list[dict]]:
    """The agent, greedy, on the test flight; its run directory and per-step infos."""
    env = caviar.gym.make(args.test, AGENT_MODULE, beam_selection_spec(UE, previous_gains=True),
                          overrides={"modules.comm.params.raytracing.samples_per_src": args.rays},
                          max_steps=args.test_steps,
                          out=args.runs / "test")
    infos = []
    try:
        obs, _ = env.reset(seed=args.seed)
        done = False
        while not done:
            obs, _, terminated, truncated, info = env.step(agent.act(obs, explore=False))
            infos.append(info)
            done = terminated or truncated
            progress.update(1)
        assert env.run_dir is not None
        return env.run_dir, infos
    finally:
        env.close()


def sweeps(run_dir: pathlib.Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steps, positions and gains of all pairs of UE ``UE`` recorded in a run, by step."""
    log = caviar.load_run(run_dir)
    gains = {int(m.step or 0): np.asarray(m.data, dtype=np.float64).ravel()
             for m in log.decoded(per_ue(BEAM_GAINS, UE))}
    positions = {int(m.step or 0): read_position(m.data) for m in log.decoded(POSITIONS) if m.data["UE_Id"] == UE}
    steps = np.array(sorted(set(gains) & set(positions)))
    return steps, np.stack([positions[k] for k in steps]), np.stack([gains[k] for k in steps])


def scores(choices: np.ndarray, gains: np.ndarray, budget: LinkBudget) -> dict[str, float]:
    """Top-1 (%), mean throughput (Mbit/s) and its share of the oracle's (%), mean reward."""
    best = gains.max(axis=1)
    mbps = budget.throughput_mbps(gains[np.arange(len(gains)), choices])
    best_mbps = budget.throughput_mbps(best)
    return {"top1_pct": 100 * float(np.mean(choices == gains.argmax(axis=1))),
            "throughput_mbps": float(mbps.mean()),
            "throughput_of_oracle_pct": 100 * float(mbps.mean() / best_mbps.mean()),
            "mean_reward": float(np.mean(mbps / best_mbps))}


def compare(args, train_runs, test_run, infos) -> tuple[dict[str, dict], dict[str, Any]]:
    """Every selector's scores on the test flight's steps."""
    budget = LinkBudget()  # sionna-link's defaults, as blueprints/beam-gym uses
    steps, positions, gains = sweeps(test_run)
    n = len(infos)
    steps, positions, gains = steps[:n], positions[:n], gains[:n]
    agent = np.array([i["pair"] for i in infos])
    measured = np.array([i["throughput_mbps"] for i in infos])
    recomputed = budget.throughput_mbps(gains[np.arange(n), agent])
    if not np.allclose(measured, recomputed, rtol=1e-6, atol=1e-9):
        raise RuntimeError("the agent's throughput measured by the environment differs from the one recomputed "
                           "from the recorded sweeps: is the link budget of the test flight sionna-link's default?")
    train_sets = [sweeps(r) for r in train_runs]
    x = np.concatenate([s[1] for s in train_sets])
    y = np.concatenate([s[2].argmax(axis=1) for s in train_sets])
    tree = train_tree(x, y, seed=args.seed)
    previous = np.r_[tree.predict(positions[:1]), gains[:-1].argmax(axis=1)]  # first step: the tree's pair
    rng = np.random.default_rng(args.seed)
    choices = {"trained agent (SweepBandit)": agent, "random": rng.integers(PAIRS, size=n),
               "paper's tree (depth 15)": tree.predict(positions).astype(int), "previous step's best": previous,
               "oracle": gains.argmax(axis=1)}
    table = {name: scores(c, gains, budget) for name, c in choices.items()}
    facts = {"train_samples": int(len(x)), "test_steps": int(n), "test_nlos_pct":
             100 * float(np.mean([not i["los"] for i in infos])),
             "agent_throughput_check": "env-measured = recomputed from the sweeps (rtol 1e-6)"}
    return table, facts


def write_report(out: pathlib.Path, report: dict, hits: list[float]) -> str:
    out.mkdir(parents=True, exist_ok=True)
    (out / "gym-baseline.json").write_text(json.dumps(report, indent=2) + "\n")
    rows = ["| selector | top-1 (%) | mean throughput (Mbit/s) | of the oracle's (%) | mean reward |",
            "|---|---:|---:|---:|---:|"]
    rows += [f"| {name} | {s['top1_pct']:.1f} | {s['throughput_mbps']:.1f} | {s['throughput_of_oracle_pct']:.1f} | "
             f"{s['mean_reward']:.3f} |" for name, s in report["table"].items()]
    table = "\n".join(rows)
    a = report["args"]
    (out / "gym-baseline.md").write_text(
        f"# Beam selection: a learning agent in the caviar.gym environment\n\n"
        f"Measured by `python -m caviar_plugins.tools.baselines.gym_baseline` (seed {a['seed']}, "
        f"{a['rays']:.0e} rays per source): trained for {a['episodes']} episodes of {a['steps']} steps "
        f"(random-waypoint flights of blueprints/beam-gym/config.toml, {report['train_samples']} steps), "
        f"evaluated on {report['test_steps']} steps of the held-out SAR-route flight (test-flight.toml; "
        f"{report['test_nlos_pct']:.0f} % NLOS). The agent's numbers are measured by the environment; the others "
        f"are scored on the same steps from the recorded sweeps of all 256 pairs. Reward = throughput of the pair / "
        f"throughput of the best pair. Training took {report['train_wall_s']:.0f} s, evaluation "
        f"{report['test_wall_s']:.0f} s.\n\n{table}\n\n"
        f"*trained agent*: ε-greedy (ε = 0.1) contextual bandit, one gradient-boosted regression of a pair's "
        f"gain from the pair's features (previous gain, neighbouring beams, rank, beam indices, position), learning "
        f"from each step's sweep. *paper's tree*: max depth {MAX_DEPTH} on (x, y, z), fitted "
        f"on the best pairs of the training episodes. *previous step's best*: needs last step's full sweep, as the "
        f"agent does. *oracle*: the best pair of the step.\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    names = list(report["table"])
    ax1.barh(names, [report["table"][k]["top1_pct"] for k in names], color="tab:blue", label="top-1 (%)")
    ax1.barh(names, [report["table"][k]["throughput_of_oracle_pct"] for k in names], color="tab:orange",
             alpha=0.5, label="throughput, % of oracle")
    ax1.set(xlabel="%", title="Held-out flight")
    ax1.invert_yaxis()
    ax1.legend(loc="lower right")
    window = 25
    curve = np.convolve(hits, np.ones(window) / window, mode="valid") if len(hits) >= window else np.array(hits)
    ax2.plot(np.arange(len(curve)) + min(window, len(hits)), 100 * curve)
    ax2.set(xlabel="training step", ylabel=f"top-1 (%), mean of {window} steps", title="Training (ε-greedy)")
    ax2.grid(True)
    fig.tight_layout()
    fig.savefig(out / "gym-baseline.png", dpi=100)
    plt.close(fig)
    return table


def main(argv=None) -> dict:
    args = parse_args(argv)
    from tqdm import tqdm

    agent = SweepBandit(seed=args.seed)
    total = args.episodes * args.steps + args.test_steps
    with tqdm(total=total, desc="beam-gym", unit="step", disable=args.quiet) as progress:
        t0 = time.monotonic()
        train_runs, hits = train(args, agent, progress)
        t1 = time.monotonic()
        test_run, infos = evaluate(args, agent, progress)
        t2 = time.monotonic()
    table, facts = compare(args, train_runs, test_run, infos)
    report = {"args": {k: str(v) if isinstance(v, pathlib.Path) else v for k, v in vars(args).items()},
              "train_runs": [str(r) for r in train_runs], "test_run": str(test_run), **facts,
              "train_wall_s": t1 - t0, "test_wall_s": t2 - t1, "train_top1_per_step": hits, "table": table}
    print(write_report(args.out, report, hits))
    return report


if __name__ == "__main__":
    main()
