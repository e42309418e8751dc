"""The one thing pyproject.toml cannot say: the wheel carries the repository's
lens prescriptions (lenses/*.toml, beside dcdi_core/ in a checkout) as
dcdi_core/lenses/, where ``optics.lens.lens_dirs`` finds them in an
installed package. Everything else is in pyproject.toml."""
import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

LENSES = Path(__file__).resolve().parent / "lenses"


class BuildWithLenses(build_py):
    def run(self):
        super().run()
        target = Path(self.build_lib) / "dcdi_core" / "lenses"
        target.mkdir(parents=True, exist_ok=True)
        for f in sorted(LENSES.glob("*")):
            if f.suffix in (".toml", ".md"):
                shutil.copyfile(f, target / f.name)


setup(cmdclass={"build_py": BuildWithLenses})
