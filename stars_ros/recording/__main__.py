"""``python -m stars_ros.recording``: repair or list interrupted bags (``bag.main``)."""
import sys

from stars_ros.recording.bag import main

sys.exit(main())
