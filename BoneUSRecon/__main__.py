"""``python -m BoneUSRecon`` runs the ``bone-us-recon`` command line."""

from BoneUSRecon.cli import entry_point

if __name__ == "__main__":
    entry_point()
