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
        (f"share/{PACKAGE}/launch", glob("launch/*.py") + glob("launch/*.xml")),
        (f"share/{PACKAGE}/rviz", glob("rviz/*.rviz")),
        (f"share/{PACKAGE}/maps", glob("maps/*.yaml") + glob("maps/*.png") + ["maps/README.md"]),
    ],
    python_requires=">=3.10",
    # what `pip install .` brings; the ROS side (rclpy, the message packages, tf2_ros) comes from a
    # ROS install (package.xml, rosdep) or from the ROS 2 wheels that requirements.txt pins.
    # Exact, tested versions: requirements.txt (direct) and constraints.txt (everything).
    install_requires=[
        "numpy>=1.24,<3",
        "scipy>=1.10,<2",
        "numba>=0.58,<1",  # optional at run time (numpy fallbacks), but the speed figures need it
        "rosbags>=0.10,<0.12",
        "apsw>=3.40",  # rosbags' SQLite reader: its errors are told apart from other failures (bags/reader.py)
        "PyYAML>=6,<7",
        "matplotlib>=3.7,<4",
        "pillow>=9,<14",
        "tqdm>=4.60,<5",
    ],
    extras_require={
        "tune": ["optuna>=4,<6"],  # localization-tune
        # localization-tune on several machines sharing one PostgreSQL database (postgresql://...): the
        # driver psycopg (psycopg[binary], pinned: the tested build), which SQLAlchemy 2.1 uses for postgresql://
        "distributed": ["optuna>=4,<6", "SQLAlchemy>=2.1,<3", "psycopg==3.3.9", "psycopg-binary==3.3.9"],
        "live": ["foxglove-sdk>=0.30,<1"],  # localization-replay --foxglove, the node's live view
        "dev": ["pytest>=8", "hypothesis>=6", "ruff>=0.5", "websockets>=13"],
    },
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
