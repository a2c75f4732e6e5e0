"""ss-drl: Smart Start + Hindsight Experience Replay for exploration in sparse-reward mazes."""

from ss_drl import envs  # noqa: F401  (registers the SSDRL/*-v0 gymnasium ids)

__version__ = "0.1.0"
