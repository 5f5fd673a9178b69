"""Matplotlib helpers shared by the diagnostics' figures (headless: the Agg backend)."""

import pathlib


def pyplot():
    """``matplotlib.pyplot`` with the non-interactive Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, png: str | pathlib.Path) -> pathlib.Path:
    """Save ``fig`` as a PNG (creating its folder) and close it."""
    png = pathlib.Path(png)
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    pyplot().close(fig)
    return png
