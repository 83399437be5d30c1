"""Keras 3 (torch backend) training and inference for KPCN denoisers.

Importing this package does not import keras or torch: the command line imports them only for the
subcommands that need them. The backend is fixed to torch before keras is first imported.
"""

import os

os.environ.setdefault("KERAS_BACKEND", "torch")
