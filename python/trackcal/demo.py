"""The main job (scripts/demo.sh). Grows with the project into the full simulate-fit-diagnose-serve loop."""

import sys

import trackcal


def main(argv=None) -> int:
    print(f"trackcal {trackcal.__version__}: native core loaded")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
