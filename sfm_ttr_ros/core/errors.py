"""The package-wide error for bad input.

Every layer raises :class:`InputError` for input it cannot use (an empty window, frames of
different sizes, bad intrinsics, an unreadable image, a parameter out of range): a
``ValueError`` with a message that says what is wrong, raised before any heavy work. A window
the method cannot refine is not an error: its outcome says why
(:mod:`sfm_ttr_ros.core.outcomes`).
"""


class InputError(ValueError):
    """Bad input given to the library (clear message, raised before any heavy work)."""


def check_choice(name: str, value: object, allowed: tuple) -> None:
    """InputError unless ``value`` is one of ``allowed`` (a config's ``__post_init__``)."""
    if value not in allowed:
        raise InputError(f"{name} must be one of {', '.join(map(str, allowed))}; got {value!r}")
