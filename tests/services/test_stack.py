"""`texelbake stack up` (`farm.stack.stack_up`) reads its tokens, Redis URL and the other
settings from the environment as the server does, and says which Redis it uses."""

from __future__ import annotations

import json

import httpx
import pytest

from farm.stack import OWN_REDIS, free_port, redis_ping, stack_down, stack_up
from texelbake.errors import SettingsError, StageError

pytestmark = [pytest.mark.service, pytest.mark.timeout(120)]


def test_stack_up_takes_tokens_and_redis_from_the_environment(tmp_path, monkeypatch):
    url = f"redis://127.0.0.1:{free_port()}/0"  # local, nothing answers: the stack starts it
    monkeypatch.setenv("TEXELBAKE_REDIS_URL", url)
    monkeypatch.setenv("TEXELBAKE_TOKENS", json.dumps({"env-token-0123456789": "studio"}))
    stack = stack_up(tmp_path / "a", workers={}, environment="test")
    try:
        assert stack.redis_url == url and "redis" in stack.commands and redis_ping(url)
        assert json.loads(stack.env["TEXELBAKE_TOKENS"]) == {"env-token-0123456789": "studio"}
        lines = stack.describe()
        assert f"redis: {url} (started by this stack)" in lines
        assert "tokens: from TEXELBAKE_TOKENS: tenants studio" in lines
        r = httpx.get(f"{stack.api_url}/api/v1/jobs",
                      headers={"Authorization": "Bearer env-token-0123456789"}, timeout=30)
        assert r.status_code == 200, r.text
    finally:
        stack_down(tmp_path / "a")
    assert not redis_ping(url)  # it stopped the Redis it started

    # a Redis it did not start is used, named as such, and left running by `down`
    other = stack_up(tmp_path / "b", workers={}, api=False, environment="test")
    try:
        monkeypatch.setenv("TEXELBAKE_REDIS_URL", other.redis_url)
        monkeypatch.delenv("TEXELBAKE_TOKENS")
        st = stack_up(tmp_path / "c", workers={}, api=False, environment="test")
        assert st.redis_url == other.redis_url and "redis" not in st.commands
        assert f"redis: {other.redis_url} (already running: not started, and not stopped, " \
               "by this stack)" in st.describe()
        assert st.tokens_from == "new"
        stack_down(tmp_path / "c")
        assert redis_ping(other.redis_url)
    finally:
        stack_down(tmp_path / "b")


def test_stack_up_starts_its_own_redis_without_a_url_and_refuses_bad_tokens(
        tmp_path, monkeypatch):
    monkeypatch.delenv("TEXELBAKE_REDIS_URL", raising=False)
    monkeypatch.setenv("TEXELBAKE_TOKENS", "[1, 2]")
    with pytest.raises(SettingsError, match="TEXELBAKE_TOKENS"):
        stack_up(tmp_path / "a", workers={}, api=False)
    assert not (tmp_path / "a" / "stack.json").exists()  # nothing was started
    monkeypatch.delenv("TEXELBAKE_TOKENS")
    # never the machine's default Redis, even where one answers on 6379
    st = stack_up(tmp_path / "b", workers={}, api=False, environment="test")
    try:
        assert "redis" in st.commands and st.redis_url != "redis://127.0.0.1:6379/0"
        assert redis_ping(st.redis_url)
    finally:
        stack_down(tmp_path / "b")


def test_ports_taken_before_the_servers_bind_them(tmp_path, monkeypatch):
    """A free port can be taken between `free_port` choosing it and uvicorn or redis-server
    binding it: the stack starts that server again on another port (Redis's new URL in the
    environment every later process gets). A port the caller named is not changed: the
    error quotes the server's log."""
    import socket

    import farm.stack as fs

    monkeypatch.setenv("TEXELBAKE_REDIS_URL", f"redis://127.0.0.1:{free_port()}/0")
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        taken = holder.getsockname()[1]
        with pytest.raises(StageError, match="(?i)address already in use"):
            stack_up(tmp_path / "named", port=taken, workers={}, environment="test")
        ports = iter([taken])
        monkeypatch.setattr(fs, "free_port", lambda: next(ports, None) or free_port())
        stack = stack_up(tmp_path / "a", workers={}, environment="test")
        try:
            assert stack.api_url != f"http://127.0.0.1:{taken}"
            assert httpx.get(stack.api_url + fs.HEALTH_PATH, timeout=30).status_code == 200
            assert "address already in use" in (tmp_path / "a/logs/api.log").read_text().lower()
            assert json.loads((tmp_path / "a/stack.json").read_text())["api_url"] == stack.api_url
        finally:
            stack_down(tmp_path / "a")
        with pytest.raises(StageError, match="(?i)address already in use"):
            stack_up(tmp_path / "named-redis", redis_url=f"redis://127.0.0.1:{taken}/0",
                     workers={}, api=False, environment="test")
        ports = iter([taken])
        stack = stack_up(tmp_path / "r", redis_url=OWN_REDIS, workers={}, environment="test")
        try:
            assert stack.redis_url != f"redis://127.0.0.1:{taken}/0" and redis_ping(stack.redis_url)
            assert stack.env["TEXELBAKE_REDIS_URL"] == stack.redis_url
            assert "address already in use" in (tmp_path / "r/logs/redis.log").read_text().lower()
            assert httpx.get(stack.api_url + fs.HEALTH_PATH, timeout=30).status_code == 200
        finally:
            stack_down(tmp_path / "r")
    # the port taken by another Redis, which answers PING: not mistaken for the stack's own
    other = stack_up(tmp_path / "other", redis_url=OWN_REDIS, workers={}, api=False,
                     environment="test")
    try:
        ports = iter([int(other.redis_url.split(":")[2].split("/")[0])])
        stack = stack_up(tmp_path / "s", redis_url=OWN_REDIS, workers={}, api=False,
                         environment="test")
        try:
            assert stack.redis_url != other.redis_url
            assert fs.redis_pid(stack.redis_url) == stack.pids["redis"]
        finally:
            stack_down(tmp_path / "s")
    finally:
        stack_down(tmp_path / "other")
