"""Train one run (or a Hydra multirun sweep): `python scripts/train.py +experiment=easy_ss_her [key=value ...]`."""

from ss_drl.cli import train_main

if __name__ == "__main__":
    train_main()
