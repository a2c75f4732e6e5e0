"""The files a run writes: the single source of truth for their names and columns.

These are a contract: plots, sweeps and external scripts parse them.

* ``episodes.csv``: one row per finished training episode (``EPISODE_COLUMNS``).
* ``eval.csv``: one row per greedy evaluation (``EVAL_COLUMNS``).
* ``summary.json``: run-level numbers (``SUMMARY_KEYS``) and the resolved config.
"""

from __future__ import annotations

EPISODES_FILE = "episodes.csv"
EVAL_FILE = "eval.csv"
SUMMARY_FILE = "summary.json"
CHECKPOINT_FILE = "checkpoint.pt"

EPISODE_COLUMNS = (
    "episode",  # 1-based index over all finished training episodes of the run (all env copies)
    "env_id",  # which env copy ran the episode
    "env_steps",  # cumulative env steps of the run (all copies) when the episode ended
    "length",  # steps in the episode
    "return",  # undiscounted return (1 on reaching G, else 0)
    "success",  # 1 if G was reached
    "smart_start",  # 1 if the episode began with a Smart Start guided phase
    "ss_target",  # the smart start state S_ss as "row:col" ("" when no guided phase)
    "ss_reached",  # 1 if the guided phase reached S_ss (within theta)
    "ss_steps",  # steps spent in the guided phase
    "epsilon",  # exploration epsilon when the episode ended
    "wall_s",  # seconds since the run started
)

EVAL_COLUMNS = (
    "env_steps",  # cumulative env steps at evaluation time
    "episode",  # finished training episodes at evaluation time
    "eval_length",  # steps of the greedy episode from S (max_steps when it fails)
    "eval_success",  # 1 if the greedy episode reached G
)

SUMMARY_KEYS = (
    "experiment",  # experiment name (e.g. "easy_ss_her")
    "method",  # method label used by plots (e.g. "ss_her", "dqn", "tabular_ss")
    "maze",  # maze name (preset or file)
    "seed",
    "completed",  # True once the run reached trainer.total_env_steps
    "first_goal_env_step",  # env steps when G was first reached (null if never)
    "first_goal_episode",  # episode index when G was first reached (null if never)
    "episodes",  # finished training episodes
    "env_steps",  # env steps taken
    "final_eval_length",  # length of the last greedy evaluation
    "optimal_length",  # BFS shortest path S -> G
    "wall_s",  # run time in seconds
    "env_steps_per_s",
    "updates_per_s",
    "config",  # the resolved Hydra config
)
