"""The one exception type for bad user input (CLI exit code 2, one plain line), and its kind for a missing extra."""


class BadInput(ValueError):
    """Bad user input; `str()` is the single line shown to the user, naming the key or path."""

    def __init__(self, where: str, problem: str):
        self.where = where
        self.problem = problem
        # one line whatever the user typed: a key or value with a line break is shown escaped
        super().__init__(f"{where}: {problem}".replace("\r", "\\r").replace("\n", "\\n"))


class MissingExtra(BadInput):
    """An optional package that a chosen value needs (team.backend=ray: Ray) is not installed: bad input, whose line
    ends with the one `pip install` that fixes it. A sweep refuses it as a whole, before any job or folder."""
