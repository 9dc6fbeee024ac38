"""The courier: a controller's commands from a thread of their own, in order, the newest setpoint counting."""

from __future__ import annotations

import threading

import pytest

from nwr.services.bridge.courier import Courier


def _blocked(courier: Courier, sent: list[str]) -> threading.Event:
    """A first command under way until the returned event is set."""
    release, entered = threading.Event(), threading.Event()

    def first() -> None:
        entered.set()
        release.wait(10.0)
        sent.append("first")

    courier.post("stop", first)
    assert entered.wait(5.0)
    return release


def test_newer_motions_and_kicks_replace_those_not_yet_sent() -> None:
    courier, sent = Courier("test"), []
    release = _blocked(courier, sent)
    for i in range(5):
        courier.post("kick", lambda i=i: sent.append(f"kick {i}"))
        courier.post("motion", lambda i=i: sent.append(f"motion {i}"))
    assert courier.busy_s() > 0.0 and not courier.idle() and sent == []
    release.set()
    assert courier.wait_idle(5.0)
    assert sent == ["first", "kick 4", "motion 4"] and courier.replaced == 8 and courier.sent == 3
    courier.close(5.0)


def test_a_stop_drops_the_motions_before_it_and_keeps_its_order() -> None:
    courier, sent = Courier("test"), []
    release = _blocked(courier, sent)
    courier.post("motion", lambda: sent.append("motion before"))
    courier.post("kick", lambda: sent.append("kick"))
    courier.post("stop", lambda: sent.append("stop"))
    courier.post("motion", lambda: sent.append("motion after"))
    release.set()
    assert courier.wait_idle(5.0)
    assert sent == ["first", "kick", "stop", "motion after"]
    courier.close(5.0)


def test_a_failed_command_drops_what_waits_and_is_told_once() -> None:
    courier, sent = Courier("test"), []
    release = _blocked(courier, sent)

    def fails() -> None:
        raise RuntimeError("no answer")

    courier.post("motion", fails)
    courier.post("kick", lambda: sent.append("kick"))
    release.set()
    assert courier.wait_idle(5.0)
    error = courier.error()
    assert isinstance(error, RuntimeError) and str(error) == "no answer"
    assert courier.error() is None and sent == ["first"]  # the kick after the failure was not sent
    courier.post("kick", lambda: sent.append("kick"))  # the courier goes on
    assert courier.wait_idle(5.0) and sent == ["first", "kick"]
    courier.close(5.0)


def test_close_sends_what_waits_then_ends_the_thread() -> None:
    courier, sent = Courier("test"), []
    release = _blocked(courier, sent)
    courier.post("stop", lambda: sent.append("stop"))
    release.set()
    courier.close(5.0)
    assert sent == ["first", "stop"] and courier.closed and courier.idle()


def test_without_a_thread_a_command_is_sent_at_once_and_raises_there() -> None:
    courier, sent = Courier("test", threaded=False), []
    courier.post("motion", lambda: sent.append("motion"))
    assert sent == ["motion"] and courier.idle() and not courier.threaded

    def fails() -> None:
        raise RuntimeError("not connected")

    with pytest.raises(RuntimeError, match="not connected"):
        courier.post("kick", fails)
