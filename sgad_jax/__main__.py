import sys

from sgad_jax.cli import main

sys.exit(main())
