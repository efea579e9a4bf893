"""rigctl: run magnetic micro-robot manipulation rigs."""


def __getattr__(name: str) -> str:
    # `rigctl.__version__` from the installed package's metadata, read when first asked for:
    # importing importlib.metadata costs tens of milliseconds every command would pay
    if name != "__version__":
        raise AttributeError(f"module 'rigctl' has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("rigctl")
    except PackageNotFoundError:  # a checkout that was never installed
        return "0+unknown"
