"""`make reproduce`: run the whole workflow on the embedded default campaign."""

import sys


def main() -> int:
    print("crashfuse reproduce: the workflow does not exist yet (issue 5); nothing to run.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
