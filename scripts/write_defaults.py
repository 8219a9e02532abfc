"""Write recon/core/presets/defaults.yaml from the config dataclasses' fields and docstrings.

Run it after changing a setting's default or docstring (tests/test_core_config_file.py fails
until then):

    python scripts/write_defaults.py
"""

from recon.core.config_file import write_defaults

if __name__ == "__main__":
    print(f"wrote {write_defaults()}")
