"""Train one run (or a Hydra multirun sweep): `python scripts/train.py +experiment=easy_ss_her [key=value ...]`.

The same as the `ss-drl-train` console script of an installed package.
"""

from ss_drl.cli import train_main

if __name__ == "__main__":
    train_main()
