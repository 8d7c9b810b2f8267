"""The one error type the CLI turns into a single line and exit code 2.

Anything the user can fix (a wrong port, model, config or episode directory) is raised as a
UserError, or as a firmware_bridge LinkError, with a message that names what is wrong. Anything
else is a bug and keeps its traceback.
"""


class UserError(Exception):
    """Bad input from the user: printed as one line, exit code 2."""


EXIT_USAGE = 2
