"""What both drivers share: the typed configuration (``config``, read from files by
``config_file``), the stages (``stages``, with the MEDeA and refinement wrappers ``medea`` and
``refine``), the frame bundle the stages hand on (``sequence``), the stage clock and the
report (``report``)."""
