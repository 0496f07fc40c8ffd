"""gradsep: gradient-domain rendering with illumination separation, reconstructed by an unsupervised network.

Installed, the repository's top-level folders are this package's subpackages (``gradsep.model`` is ``model/``,
setup.py). In a source checkout that is not installed -- the repository root on ``sys.path``, this file found
there first -- the same names resolve because the root is added to this package's search path.
"""

from pathlib import Path as _Path

_root = _Path(__file__).resolve().parent.parent
if not (_Path(__file__).resolve().parent / "model").is_dir() and (_root / "model" / "__init__.py").is_file():
    __path__.append(str(_root))  # noqa: F821 -- the package's own search path

from gradsep.model import __version__  # noqa: E402

__all__ = ["__version__"]
