"""Throughput benchmarks of ss-drl, run from the checkout by ``scripts/benchmark.py`` (not part of the installed
package: they import Stable-Baselines3, the ``bench`` extra, and read the checkout's ``conf/``).

``python scripts/benchmark.py [--section env|train|planner|her|update|all] [--repeats R] [--threads T] [--quick]``
prints the exact command line, the library versions and one markdown table per section. Every number is the median
of R repeats. All sections run with one torch thread (the trainer's default, ``trainer.torch_threads: 1``) unless
``--threads`` says otherwise. ``--quick`` shrinks every section (:data:`benchmarks.cli.QUICK_SIZES`): a smoke run.

Sections, one module each:

* :mod:`benchmarks.env`: env steps/s of the raw gymnasium env, TorchRL's ``GymEnv`` and the native batched env.
* :mod:`benchmarks.train`: training throughput of ss-drl against Stable-Baselines3 ``DQN`` + ``HerReplayBuffer``.
* :mod:`benchmarks.planner`: ms per Smart Start decision (UCB selection + value iteration) on explored mazes.
* :mod:`benchmarks.her`: ms per ``HindsightReplayBuffer.sample()`` at each stored size.
* :mod:`benchmarks.update`: ms per ``DQNAgent.update()`` of the replay-only and the model-bounded DQN, against the
  same learner with no bound.

Each ``bench_*`` function takes its sizes as arguments and returns the section's markdown; :mod:`benchmarks.cli`
holds the command line and :mod:`benchmarks.common` the shared helpers.
"""
