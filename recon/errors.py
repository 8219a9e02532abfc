"""The one exception type for bad user input.

Anything the user can fix (missing file, unreadable video, mismatched sizes, bad pose
file, NaN depth, ...) raises :class:`ReconInputError` with a single line that says what is
wrong and where (file, frame, line). The CLI prints it without a traceback and exits 2.
"""


class ReconInputError(ValueError):
    """Bad input from the user: one line, naming the file/frame/line at fault."""

    exit_code = 2
