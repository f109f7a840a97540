"""The real data beside the checkout (``../shared/data``) for the tests that read it, skipping when it is absent."""
from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def hololens_or_skip():
    """(views, truth) of the real HoloLens indoor sequence, or a skip naming where it was looked for."""
    from eonav.io.datasets import hololens_sequence
    if not (DATA / "hololens_dvmvs_20f").is_dir():
        pytest.skip(f"real data not found at {DATA / 'hololens_dvmvs_20f'} (../shared/data)")
    return hololens_sequence(DATA)
