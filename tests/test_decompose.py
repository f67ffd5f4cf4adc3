"""Text decomposition: the keyword decomposer's routing, and the LLM backend against a local fake
OpenAI-compatible server on 127.0.0.1 (never the network)."""

from __future__ import annotations

import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from dualflow.decompose import (
    FEW_SHOT,
    NOT_SPECIFIED,
    KeywordDecomposer,
    LLMDecomposer,
    build_messages,
    clauses,
    find_cues,
    make_decomposer,
)
from dualflow.errors import DualFlowError


def test_keyword_routing_of_clauses():
    d = KeywordDecomposer().decompose(
        "The two dancers hold hands facing each other, the follower spins under his raised arm, "
        "then they step quickly on the beat."
    )
    assert (
        "hold hands facing each other" in d.spatial and "hand-to-hand" in d.spatial and "facing each other" in d.spatial
    )
    assert "spins under his raised arm" in d.body and "spin" in d.body and "arm" in d.body
    assert "step quickly on the beat" in d.rhythm and "fast" in d.rhythm and "on the beat" in d.rhythm
    assert "spins" not in d.rhythm and "quickly" not in d.spatial


def test_keyword_decomposer_is_deterministic_and_never_invents():
    k = KeywordDecomposer()
    assert k.decompose("Hello there.") == k.decompose("Hello there.")
    empty = k.decompose("Hello there.")
    assert empty.as_tuple() == (NOT_SPECIFIED["spatial"], NOT_SPECIFIED["body"], NOT_SPECIFIED["rhythm"])
    only_body = k.decompose("She kicks her left leg.")
    assert only_body.spatial == NOT_SPECIFIED["spatial"] and only_body.rhythm == NOT_SPECIFIED["rhythm"]
    assert "kick" in only_body.body and "leg" in only_body.body


def test_cues_match_whole_words_only():
    assert find_cues("a slowdown of the barmaid")["rhythm"] == {}
    assert find_cues("a hand-in-hand walk")["spatial"]["connection"] == ["hand-to-hand"]
    assert clauses("A, b; c while d. E then f") == ["A", "b", "c", "d", "E", "f"]


def test_synthetic_template_text_decomposes_into_all_three(tmp_path):
    from dualflow.synthetic import make_duet

    text = make_duet("mirror", seconds=1.0, fps=30.0, seed=3).text
    d = KeywordDecomposer().decompose(text)
    assert all(s not in NOT_SPECIFIED.values() for s in d.as_tuple()), (text, d)


class _FakeLLM(BaseHTTPRequestHandler):
    replies: list[tuple[int, str]] = []
    received: list[dict] = []

    def do_POST(self):  # noqa: N802 (http.server's naming)
        body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
        type(self).received.append({"path": self.path, "auth": self.headers.get("Authorization"), "body": body})
        status, content = type(self).replies.pop(0)
        payload = json.dumps({"choices": [{"message": {"role": "assistant", "content": content}}]}).encode()
        if status != 200:
            payload = b'{"error": "boom"}'
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(payload)))
        self.end_headers()
        self.wfile.write(payload)

    def log_message(self, *args):
        pass


@pytest.fixture
def fake_llm():
    _FakeLLM.replies, _FakeLLM.received = [], []
    server = ThreadingHTTPServer(("127.0.0.1", 0), _FakeLLM)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}/v1", _FakeLLM
    server.shutdown()
    server.server_close()
    thread.join(timeout=5)


ANSWER = {"spatial": "Closed position, facing.", "body": "Arms wave.", "rhythm": "Fast, on the beat."}


def test_llm_request_follows_the_paper_prompt_and_caches(fake_llm, tmp_path, monkeypatch):
    url, handler = fake_llm
    monkeypatch.setenv("DUALFLOW_LLM_URL", url)
    monkeypatch.setenv("DUALFLOW_LLM_API_KEY", "secret-test-token")
    handler.replies.append((200, "```json\n" + json.dumps(ANSWER) + "\n```"))
    cache = tmp_path / "decomp.jsonl"
    llm = make_decomposer("llm", model="local-model", cache_path=cache)
    d = llm.decompose("They hold hands and spin fast.", genre="swing")
    assert d.to_dict() == {k: v.strip() for k, v in ANSWER.items()}

    (req,) = handler.received
    assert req["path"] == "/v1/chat/completions" and req["auth"] == "Bearer secret-test-token"
    msgs = req["body"]["messages"]
    assert req["body"]["model"] == "local-model"
    assert msgs[0]["role"] == "system" and "swing" in msgs[0]["content"] and "spatial" in msgs[0]["content"]
    assert (
        msgs[1]["role"] == "system"
        and "Reference guidelines" in msgs[1]["content"]
        and "hand-to-hand" in msgs[1]["content"]
    )
    shots = msgs[2:-1]
    assert [m["role"] for m in shots] == ["user", "assistant"] * 3
    assert shots[0]["content"] == FEW_SHOT["swing"][0][0]
    assert set(json.loads(shots[1]["content"])) == {"spatial", "body", "rhythm"}
    assert msgs[-1] == {"role": "user", "content": "They hold hands and spin fast."}

    # Cached: same text again -> no request; a fresh decomposer reads the JSONL.
    assert llm.decompose("They hold hands and spin fast.", genre="swing") == d
    again = LLMDecomposer(model="local-model", cache_path=cache)
    assert again.decompose("They hold hands and spin fast.", genre="swing") == d
    assert len(handler.received) == 1 and again.requests == 0
    (line,) = cache.read_text().splitlines()
    assert json.loads(line)["text"] == "They hold hands and spin fast."
    # A different genre is a different prompt: asked again.
    handler.replies.append((200, json.dumps(ANSWER)))
    again.decompose("They hold hands and spin fast.", genre="latin")
    assert len(handler.received) == 2


def test_llm_errors_are_clear(fake_llm, tmp_path, monkeypatch):
    url, handler = fake_llm
    monkeypatch.delenv("DUALFLOW_LLM_URL", raising=False)
    with pytest.raises(DualFlowError, match="DUALFLOW_LLM_URL"):
        make_decomposer("llm")
    llm = LLMDecomposer(url=url, cache_path=tmp_path / "c.jsonl")
    handler.replies.append((500, ""))
    with pytest.raises(DualFlowError, match="HTTP 500"):
        llm.decompose("a")
    handler.replies.append((200, "I think the spatial part is..."))
    with pytest.raises(DualFlowError, match="not a JSON object"):
        llm.decompose("b")
    handler.replies.append((200, json.dumps({"spatial": "x", "body": ""})))
    with pytest.raises(DualFlowError, match=r"\['body', 'rhythm'\]"):
        llm.decompose("c")
    assert not (tmp_path / "c.jsonl").exists()  # nothing half-written
    # A crash-truncated last line is ignored; a bad line in the middle is an error.
    good = json.dumps({"key": "k", **ANSWER})
    (tmp_path / "d.jsonl").write_text(good + "\n" + '{"key": "tru')
    assert len(LLMDecomposer(url=url, cache_path=tmp_path / "d.jsonl")._cache) == 1
    (tmp_path / "e.jsonl").write_text("garbage\n" + good + "\n")
    with pytest.raises(DualFlowError, match="e.jsonl:1"):
        LLMDecomposer(url=url, cache_path=tmp_path / "e.jsonl")
    with pytest.raises(DualFlowError, match="cannot connect"):
        LLMDecomposer(url="http://127.0.0.1:9", timeout_s=2).decompose("x")
    with pytest.raises(DualFlowError, match="unknown decomposer"):
        make_decomposer("gpt")


def test_messages_fall_back_to_the_default_examples():
    msgs = build_messages("text", genre="polka")
    assert "polka" in msgs[0]["content"] and len(msgs) == 2 + 6 + 1
