import sys

from spk2img.cli import main

if __name__ == "__main__":
    sys.exit(main())
