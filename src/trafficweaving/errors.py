"""The one exception type for bad user input; the CLI prints it as a one-line message."""


class InputError(ValueError):
    """Bad input from a user (file, option or value); its message names the file and what was expected."""
