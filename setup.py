"""The package layout (everything else is in pyproject.toml).

One installed name, ``gradsep``: the design's top-level folders are its subpackages -- ``model/`` installs as
``gradsep.model``, ``renderer/`` as ``gradsep.renderer``, and so on -- so nothing generic (``model``, ``service``,
...) lands in site-packages. A role-specific build context may leave folders out (the serving image copies no
``renderer/``, ``training/`` or ``evaluation/``): only the folders present are packaged, and the command line
skips the absent roles' commands.
"""

from pathlib import Path

from setuptools import find_packages, setup

HERE = Path(__file__).resolve().parent
FOLDERS = ("model", "renderer", "service", "training", "evaluation")

package_dir = {"gradsep": "gradsep"}
packages = ["gradsep"]
for folder in FOLDERS:
    if (HERE / folder / "__init__.py").is_file():
        package_dir[f"gradsep.{folder}"] = folder
        packages += [f"gradsep.{folder}"] + [f"gradsep.{folder}.{sub}" for sub in find_packages(where=folder)]

setup(packages=packages, package_dir=package_dir)
