"""ament_python package `localization` (also pip-installable into a plain virtual environment)."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "localization"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
        (f"share/{PACKAGE}/rviz", glob("rviz/*.rviz")),
        (f"share/{PACKAGE}/maps", glob("maps/*.yaml") + glob("maps/*.png") + ["maps/README.md"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="localization maintainers",
    maintainer_email="localization@example.com",
    description="Monte Carlo Localization for car-like robots in a known 2D map (ROS 2 Jazzy).",
    license="MIT",
    entry_points={
        "console_scripts": [
            "particle_filter = localization.particle_filter:main",
            "particle_filter_lifecycle = localization.ros.lifecycle_node:main",
            "localization-play = localization.tools.play:main",
            "localization-simulate = localization.tools.simulate:main",
            "localization-replay = localization.tools.replay:main",
            "localization-demo = localization.tools.demo:main",
            "localization-calibrate = localization.tools.calibrate:main",
            "localization-tune = localization.tools.tune:main",
        ],
    },
)
