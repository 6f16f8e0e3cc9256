"""``gcgs params``: compose conf/ into params.yaml, or check that it is up to date."""
from __future__ import annotations

import argparse

from pipeline.config.params import PARAMS_PATH, compose_params, dump_params


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--write", action="store_true", help="write params.yaml")
    p.add_argument("--check", action="store_true", help="exit 1 if params.yaml differs from conf/")
    p.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. synth.seed=3")


def run(args: argparse.Namespace) -> int:
    text = dump_params(compose_params(args.overrides))
    if args.check:
        current = PARAMS_PATH.read_text() if PARAMS_PATH.is_file() else ""
        if current != text:
            print("params.yaml is stale: run `gcgs params --write`")
            return 1
        return 0
    if args.write:
        PARAMS_PATH.write_text(text)
        print(f"wrote {PARAMS_PATH}")
    else:
        print(text, end="")
    return 0
