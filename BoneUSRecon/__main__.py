"""``python -m BoneUSRecon`` runs the ``bone-us-recon`` command line."""

import sys

from BoneUSRecon.cli import main

if __name__ == "__main__":
    sys.exit(main())
