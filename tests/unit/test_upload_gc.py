"""The upload path pauses the cyclic GC while it builds a document, and always restores it."""

import gc
import threading

import pytest

from services.uploads import cyclic_gc_paused

pytestmark = pytest.mark.unit


def test_pause_disables_and_restores_the_collector():
    assert gc.isenabled()
    with cyclic_gc_paused():
        assert not gc.isenabled()
    assert gc.isenabled()


def test_overlapping_pauses_resume_only_when_the_last_leaves():
    inside, release = threading.Event(), threading.Event()

    def other_upload():
        with cyclic_gc_paused():
            inside.set()
            release.wait(5)

    t = threading.Thread(target=other_upload)
    t.start()
    inside.wait(5)
    with cyclic_gc_paused():
        pass
    assert not gc.isenabled()  # the other upload is still building its document
    release.set()
    t.join(5)
    assert gc.isenabled()


def test_an_error_inside_restores_the_collector_and_a_disabled_one_stays_disabled():
    with pytest.raises(ValueError), cyclic_gc_paused():
        raise ValueError("bad upload")
    assert gc.isenabled()
    gc.disable()
    try:
        with cyclic_gc_paused():
            pass
        assert not gc.isenabled()
    finally:
        gc.enable()
