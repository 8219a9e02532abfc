"""The command line: ``recon run`` and its options (``cli``; ``cli_args`` the parser,
``cli_config`` the configs it makes), ``recon view``, ``recon demo``, ``recon batch``; each
command calls the library (:mod:`recon.pipeline`, :mod:`recon.io`, :mod:`recon.export`) and
prints."""

import os

# torch's CPU allocator puts tensors of 2 MB and more on transparent huge pages when this is
# set, read once at its first allocation: before anything imports torch. A run's fresh pages
# then fault in 2 MB at a time instead of 4 kB. THP_MEM_ALLOC_ENABLE=0 turns it off.
# why: docs/decisions.md#huge-pages-for-torchs-tensors
os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")
