"""Shared test set-up: a predictable Warp kernel cache, the device list, the shared data folder."""

import os
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
os.environ.setdefault("WARP_CACHE_PATH", str(REPO / ".warp_cache"))

SHARED = REPO.parent / "shared"
TOY_DIR = REPO / "tests" / "data" / "sbki_toy"


def available_devices() -> list[str]:
    from evsemmap_warp.core.warp_runtime import init_warp

    wp = init_warp()
    return ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])


DEVICES = available_devices()


@pytest.fixture(params=DEVICES)
def device(request):
    return request.param


def shared_path(*parts: str) -> Path:
    """A path under ../shared, or a skip that says why when the checkout has no ../shared."""
    path = SHARED.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"{path} is absent: this test needs the project's shared data folder beside the checkout (CI has it)")
    return path


def wait_until(predicate, timeout: float, interval: float = 0.05) -> bool:
    """Whether ``predicate()`` came true within ``timeout`` seconds (asked every ``interval``): the viewer tests wait
    on threads, servers and browsers this way."""
    end = time.time() + timeout
    while time.time() < end:
        if predicate():
            return True
        time.sleep(interval)
    return False
