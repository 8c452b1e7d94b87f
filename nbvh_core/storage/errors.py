"""The one error every reader of this layer raises: the message says which file and why, in one line."""


class NBVHFileError(ValueError):
    """A file that is not a readable .nbvh model: the message says which file and why."""
