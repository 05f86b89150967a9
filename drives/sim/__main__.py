"""``python -m drives.sim --node N --interface I --channel C``: one simulated drive process."""

import argparse
import sys

from drives.sim.service import add_arguments, run


def main() -> int:
    """Parse the command line and run the drive until SIGINT or SIGTERM."""
    parser = argparse.ArgumentParser(
        prog="python -m drives.sim", description="Simulated CiA 402 drive (CSP) on a CAN bus."
    )
    add_arguments(parser)
    return run(parser.parse_args())


if __name__ == "__main__":
    sys.exit(main())
