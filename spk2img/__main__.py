import sys

from spk2img.cli import main

sys.exit(main())
