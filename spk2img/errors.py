"""Errors that mean "the input is wrong" (as opposed to a bug): the CLI prints them as one line
and exits non-zero; the service answers them with a 4xx and a JSON ``detail``."""


class InputError(ValueError):
    """Base of every error caused by what a user gave: files, sizes, centres, parameters."""
