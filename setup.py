"""
Everything else is in setup.cfg; this file ships ``sb3_soup_zoo.pth`` (the RL Zoo import hook, see
``_sb3_soup_zoo_hook.py``) at the top of site-packages, like pytest-cov's ``pytest-cov.pth``, and installs the
repository's top-level ``hyperparams/`` folder (the RL Zoo's layout) as the package ``sb3_soup.hyperparams``.

A wheel gets the file at its root (so pip lists it in RECORD and ``pip uninstall`` removes it); an editable install
(PEP 660) gets it in the editable wheel, whose root setuptools points ``install_lib`` at.
"""

import os

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py

PTH_FILE = "sb3_soup_zoo.pth"


class BuildPyWithPth(build_py):
    """``build_py`` that also copies ``sb3_soup_zoo.pth`` to the top of the wheel."""

    def run(self) -> None:
        super().run()
        if self.editable_mode:
            # editable_wheel builds nothing into build_lib: the wheel's files are written to install_lib
            target_dir = self.get_finalized_command("install").install_lib
        else:
            target_dir = self.build_lib
        source = os.path.join(os.path.dirname(os.path.abspath(__file__)), PTH_FILE)
        self.copy_file(source, os.path.join(target_dir, PTH_FILE), preserve_mode=False)


setup(
    cmdclass={"build_py": BuildPyWithPth},
    packages=[*find_packages(include=["sb3_soup", "sb3_soup.*"]), "sb3_soup.hyperparams"],
    package_dir={"sb3_soup.hyperparams": "hyperparams"},
    package_data={"sb3_soup": ["version.txt", "py.typed"], "sb3_soup.hyperparams": ["*.yml"]},
)
