"""``python -m gradsep.training ARGS`` (and ``torchrun -m gradsep.training ARGS``): `gradsep train ARGS` without the
command-line package; each torchrun worker runs this module. Its own module, so that training.train (which the
command module imports when it runs) never imports the command module back."""

import sys

from gradsep.training.commands import train_main

sys.exit(train_main(sys.argv[1:]))
