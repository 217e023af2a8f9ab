import sys

from sfm_ttr_ros.tools.cli import main

sys.exit(main())
