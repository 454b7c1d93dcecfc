"""`handtrain`: train the project's networks on this machine (needs the `train` extra: torch, tqdm, onnx).

    handtrain iknet [--resume] [--iters N] [--export-only] ...    (handmocap/training/train_iknet.py)
    handtrain detnet [--backbone fast|paper] [--resume] [--iters N] [--data DIR ...]    (handmocap/training/train_detnet.py)
    handtrain finder [--resume] [--iters N] [--export-only] ...   (handmocap/training/train_finder.py)

Each network is one subcommand: a module with add_arguments(parser) and main(args).
"""
import argparse
import importlib

SUBCOMMANDS = {
    "iknet": ("handmocap.training.train_iknet", "IKNet: joint rotations from 3D joints"),
    "detnet": ("handmocap.training.train_detnet", "DetNet: 2D/3D joints, presence, handedness from a hand crop"),
    "finder": ("handmocap.training.train_finder", "hand finder: hand boxes in a whole frame"),
}


def main(argv=None):
    parser = argparse.ArgumentParser(prog="handtrain", description=__doc__.splitlines()[0])
    subparsers = parser.add_subparsers(dest="network", required=True)
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        module = importlib.import_module(module_name)
        sub = subparsers.add_parser(name, help=help_text, description=module.__doc__,
                                    formatter_class=argparse.RawDescriptionHelpFormatter)
        module.add_arguments(sub)
        sub.set_defaults(run=module.main)
    args = parser.parse_args(argv)
    args.run(args)


if __name__ == "__main__":
    main()
