"""``python -m pmask.runtime.servo --include | --sources``: where the servo core's C files are."""
import sys

from pmask.runtime.servo import main

sys.exit(main())
