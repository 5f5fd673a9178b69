import os

from setuptools import find_packages, setup

with open(os.path.join("sb3_pevfa", "version.txt")) as file_handler:
    __version__ = file_handler.read().strip()

with open("README.md") as file_handler:
    long_description = file_handler.read()

# rl-zoo3's enjoy imports `requests`, its plots need `seaborn` and its Optuna report `pandas`, undeclared by it;
# PostgreSQL storages of Optuna need psycopg (SQLAlchemy 2 default driver); plotly draws Optuna's interactive plots
# of a study (examples/optuna_search.py).
ZOO = ["rl_zoo3>=2.4.0", "optuna>=4.0", "requests", "seaborn", "pandas", "psycopg[binary]", "plotly"]

setup(
    name="sb3-pevfa",
    version=__version__,
    description="Policy-extended Value Function Approximators (PPO-PeVFA) for Stable-Baselines3",
    long_description=long_description,
    long_description_content_type="text/markdown",
    packages=[package for package in find_packages() if package.startswith("sb3_pevfa")],
    package_data={"sb3_pevfa": ["py.typed", "version.txt", "hyperparams/*.yml"]},
    entry_points={
        "console_scripts": [
            "sb3-pevfa-train=sb3_pevfa.train:main",
            "sb3-pevfa-enjoy=sb3_pevfa.enjoy:main",
            "sb3-pevfa-record-video=sb3_pevfa.record_video:main",
        ]
    },
    python_requires=">=3.10",
    install_requires=[
        "stable_baselines3>=2.4.0,<3.0",
        # the time feature of the authors' protocol (sb3_pevfa.protocols.make_authors_env)
        "sb3-contrib>=2.4.0",
        # The CPU wheel 2.13.0 satisfies this range: install it first on CPU-only machines.
        # >= 2.4: fused Adam on CPU (PeVFA policies' default optimizer settings).
        "torch>=2.4,<3.0",
        "gymnasium>=1.0",
        "numpy>=1.24",
        # learn(progress_bar=True)
        "tqdm",
        "rich",
    ],
    extras_require={
        "mujoco": ["gymnasium[mujoco]>=1.0"],
        # LunarLanderContinuous-v3, one of the paper's six tasks (benchmarks/campaign.py)
        "box2d": ["gymnasium[box2d]>=1.0"],
        "zoo": ZOO,
        "tests": [
            "pytest",
            "pytest-xdist",
            "ruff",
            "gymnasium[mujoco]>=1.0",
            *ZOO,
            # rl-zoo3's record_video of classic-control tasks renders with pygame
            "gymnasium[classic-control]",
            "matplotlib",
            "scikit-learn",
            "scipy",
            "tensorboard",
            # the documentation is built (warnings as errors) by the test suite
            "sphinx",
            "myst-parser",
            "sphinx-rtd-theme",
        ],
        # diagnostics: plots, t-SNE / PCA, rank correlations, TensorBoard logs
        "diagnostics": ["matplotlib", "scikit-learn", "scipy", "tensorboard"],
        # the API pages import every documented module: rl_zoo.hyperparams_opt needs rl-zoo3 and Optuna
        "docs": ["sphinx", "myst-parser", "sphinx-rtd-theme", "matplotlib", "scikit-learn", *ZOO],
    },
    license="MIT",
    classifiers=[
        "Programming Language :: Python :: 3",
        "Topic :: Scientific/Engineering :: Artificial Intelligence",
    ],
)
