"""The prose of results.md: the legend of its tables and figures, and what the on-track
table measures. Text only: `tables.py` places it."""

from __future__ import annotations

from dqnlab.analysis.report.reference import AGENTS, REFERENCE_PROTOCOL
from dqnlab.analysis.report.runs import ALL_EQUAL, NOT_GROUPED

# Which of Dopamine's agents a configuration is compared with (reference.reference_agent).
MATCHING_TEXT = (
    f"{AGENTS['dqn'].name} for the Nature DQN's parts (whatever its optimizer, exploration "
    f"or episodes), {AGENTS['c51'].name} for C51 alone, {AGENTS['rainbow'].name} for C51 "
    "with n-step returns and prioritized replay, with or without the full Rainbow's double "
    "Q-learning, dueling head and noisy nets; none for the other variants"
)

LEGEND = [
    "- **Score**: the final evaluation of each run's best network (the network of the "
    "periodic evaluation with the highest mean), or its last where its protocol says so "
    '(`final_eval_network = "last"`, Atari 100k\'s): whole games of at most '
    "final_eval_max_episode_frames frames (5 minutes in the Nature protocol) at "
    "eval_epsilon, after random no-op starts. With one seed: that run's mean ± s.d. over "
    "its games. With several seeds: the mean of the seeds' means ± the s.d. of the seeds' "
    "means; **Seed means** gives the lowest and highest of them. Standard deviations are "
    "population ones (numpy, ddof 0), as the final evaluation's own.",
    "- **Configuration**: the settings that differ between runs of the same game; runs "
    "that differ only in `seed` are the seeds of one configuration. Settings that do not "
    "change what is learned, and the number of final-evaluation games, never label a "
    "configuration: "
    + ", ".join(f"`{name}`" for name in NOT_GROUPED if name != "seed")
    + ". Runs with different budgets (`total_steps`) are therefore seeds of one "
    "configuration (with a note); **Budget (steps)** gives their total_steps.",
    f"- **{ALL_EQUAL}**: every run of the game has the same settings but for the seed.",
    "- **Games/seed**: final-evaluation games per seed (Nature: 30).",
    "- **Nature DQN**: Mnih et al. 2015, Extended Data Table 2: mean ± s.d. over 30 games.",
    '- **Seed paper**: Roderick, MacGlashan and Tellex 2017, "Implementing the Deep '
    'Q-Network", Table 1 (Pong, Breakout and Seaquest only).',
    "- **HNS %**: human-normalised score, 100 × (score − random) / (human − random), "
    "with `random` from dqn_zoo (equal to Nature's) and two human baselines: **dqn_zoo "
    "human**, the set DeepMind's later code (dqn_zoo `atari_data.py`) uses, and **Nature "
    "human**, the human tester of the Nature paper (ED Table 2). They differ for 34 of the "
    "49 games (Pong 14.6 against 9.3), so compare only scores with the same baseline. "
    "Empty for games outside the reference table (non-Atari environments, Gymnasium ids "
    "such as ALE/Pong-v5) and for Nature human outside the Nature 49.",
    "- **Across games**: the median and mean HNS % of each configuration over its games "
    "that have the baseline (at least 2), with Nature DQN's over the same games where "
    "every one of them has a Nature DQN score.",
    '- **Aggregates across games** (Agarwal et al., NeurIPS 2021, "Deep Reinforcement '
    'Learning at the Edge of the Statistical Precipice", computed with their library '
    "rliable): each run's final-evaluation mean as HNS % with one human baseline "
    "(`--baseline`), over the games every configuration has. **IQM**: the interquartile "
    "mean, the mean of the middle half of all run scores (runs × games), less swayed by "
    "a few games than the mean and less noisy than the median; **Median** and **Mean**: of "
    "the games' means over their runs (those kept: see the notes); **Optimality gap**: "
    "100 minus the mean score with scores above human counted as 100 (how far from human; "
    "lower is better). In brackets: "
    "the 95% percentile confidence interval of a stratified bootstrap (**Resampled**: the "
    "runs within each game; the games where a configuration has one seed per game). "
    "**Performance profiles**: the fraction of all runs scoring above each τ. **P(X > Y)**: "
    "the probability of improvement, the chance that a run of X scores higher than a run "
    "of Y on the same game (ties half), averaged over the games; P(Y > X) = 1 − P(X > Y).",
    "- **Learning curves**: the mean score of the periodic evaluations (eval_steps agent "
    "steps at eval_epsilon every eval_period_steps; the mean of the games finished within "
    "the budget) against training steps, training frames on the top axis (measured from "
    "evaluations.csv: action_repeat_frames per step plus no-op starts). One line per "
    "configuration, the mean over the seeds that have an evaluation at that step; shaded: "
    "lowest to highest seed (configurations with 2 seeds or more). Behind them (Atari "
    "games, unless `--reference none`): Dopamine's published curve of the agent each "
    f"configuration matches ({MATCHING_TEXT}: a note says why), scores of its "
    f"{REFERENCE_PROTOCOL}. Each agent once, "
    "the mean of its runs in each 1M-frame window as a step, lowest to highest run shaded, "
    "in its own colour. Under them, where "
    "the runs logged them: Nature Fig. 2's held-out statistics at each periodic evaluation, "
    "the mean max over actions of the target network's Q at the next states of "
    "heldout_transitions transitions drawn once from the replay at replay start, and their "
    "mean absolute TD error, clipped at td_error_clip as in the update (DeepMind's "
    "NeuralQLearner compute_validation_statistics: v_avg and tderr_avg).",
]

ON_TRACK_TEXT = (
    "Each run measured as the reference measures: the mean raw score of its training games "
    "(whole games, at the training epsilon; `episodes.csv`) that ended in its latest 1M-frame "
    "window with a finished game, beside the reference's mean and lowest-to-highest run in "
    "the same window. **Reference**: Dopamine's curve of the agent the run matches "
    f"(data/README.md; {MATCHING_TEXT}: the verdict says why), scores of its "
    f"{REFERENCE_PROTOCOL}. Its training epsilon "
    "is 0.01 after 1M frames and its actions are sticky, while the nature preset trains at "
    "an epsilon falling from 1 to 0.1 over 4M frames, so early windows of a nature run sit "
    "lower by design: read the verdict as a sanity check, not a test. A window still being "
    "filled says how far it got. **Latest evaluation**: the run's latest periodic evaluation "
    "(eval_epsilon), the learning curve's last point."
)
