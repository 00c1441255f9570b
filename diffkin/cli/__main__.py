"""``python -m diffkin.cli ...`` (what ``torchrun ... -m diffkin.cli ik ...`` runs): the ``diffkin``
command."""

import sys

from . import main

sys.exit(main())
