#!/usr/bin/env python3
"""Learning results as a fingerprint (`psl_bench.learning_identity`): record them, check them.

    scripts/learning_identity.py record docs/learning_identity.json   # before a change
    scripts/learning_identity.py check docs/learning_identity.json    # on any machine
    scripts/learning_identity.py check --bit-identical F              # after a restructuring,
                                                                      # on the recording machine

Run it after ``source scripts/env.sh``; exit 1 when something differs.
"""
import sys

from psl_bench.learning_identity import main

if __name__ == '__main__':
    sys.exit(main())
