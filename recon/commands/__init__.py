"""The command line: ``recon run`` and its options (``cli``; ``cli_args`` the parser,
``cli_config`` the configs it makes), ``recon view``, ``recon demo``, ``recon batch``; each
command calls the library (:mod:`recon.pipeline`, :mod:`recon.io`, :mod:`recon.export`) and
prints."""
