"""Errors shown to users as one clear line (the CLI prints them without a traceback)."""


class UserError(Exception):
    """Bad input or a failed precondition the user can fix; the message is the whole story."""
