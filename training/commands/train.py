"""``unipixie train``: train (or resume) the UniPixie model on a dataset directory."""

from __future__ import annotations

NAME = "train"
HELP = "train or resume the material model on a dataset of training samples (single process; see torchrun for several GPUs)"
EXAMPLES = """  unipixie train --data dataset/ --out runs/base --steps 20000 --batch 4
  unipixie train --data dataset/ --out runs/base --steps 40000 --batch 4 --resume
  unipixie train --data dataset/ --out runs/small --preset small --save-dtype bfloat16
  torchrun --nproc_per_node=2 -m unipixie.training.train --data dataset/ --out runs/ddp --batch 8"""


def add_arguments(p):
    from ..train import add_arguments as training_arguments

    training_arguments(p)


def run(args) -> int:
    from ..train import report, settings_from_args, train

    settings = settings_from_args(args)
    stats = train(settings)
    print(report(stats, settings.out))
    return 0
