import sys

from pmask.pipeline.cli import main

sys.exit(main())
