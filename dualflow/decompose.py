"""Text decomposition into the paper's three focused descriptions (sec. 3.2, app. C).

Contract: ``decomposer.decompose(text, genre=None)`` returns :class:`FocusedDescriptions`
(spatial relationship, body movement, rhythm), three non-empty strings, each a retrieval query
of its own (:mod:`dualflow.retrieval`). :class:`KeywordDecomposer` (default) is offline and
deterministic; :class:`LLMDecomposer` (optional) asks an OpenAI-compatible endpoint named by
``DUALFLOW_LLM_URL`` and caches replies. :func:`make_decomposer` picks one by name
("keywords" | "llm"). How each works: docs/model.md.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import urllib.error
import urllib.request
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

from dualflow.errors import DualFlowError

ASPECTS = ("spatial", "body", "rhythm")

#: Reference guidelines as data: aspect -> cluster -> {canonical label: trigger phrases}.
#: Phrases match whole words, case-insensitively; the label is what the summary says.
KEYWORD_CLUSTERS: dict[str, dict[str, dict[str, tuple[str, ...]]]] = {
    "spatial": {
        "position": {
            "closed position": ("closed position", "closed hold", "close hold", "embrace", "embraces", "hug", "hugs"),
            "open position": ("open position", "open hold", "arm's length", "arms length"),
            "separated": ("separated", "apart", "separate", "distance", "away from", "backs away", "retreats"),
            "close together": ("close to", "closer", "near", "approaches", "approach", "towards", "toward"),
            "side by side": ("side by side", "beside", "next to", "alongside", "shoulder to shoulder"),
            "circling": ("around each other", "circles", "circle", "orbits", "orbit", "walks around"),
            "behind / in front": ("behind", "in front of", "follows behind"),
        },
        "orientation": {
            "facing each other": ("facing each other", "face each other", "face to face", "faces", "facing"),
            "back to back": ("back to back",),
            "turned away": ("turns away", "turned away", "facing away"),
            "mirrored": ("mirror", "mirrors", "mirrored", "mirroring", "reflection"),
        },
        "connection": {
            "hand-to-hand": (
                "hand hold",
                "handhold",
                "hold hands",
                "holds hands",
                "holding hands",
                "hand in hand",
                "hand-to-hand",
                "hands joined",
                "joined hands",
                "takes her hand",
                "takes his hand",
                "takes the hand",
                "grabs the hand",
                "handshake",
                "shake hands",
                "shakes hands",
            ),
            "hand-to-body": (
                "hand on",
                "on the shoulder",
                "on the waist",
                "on the back",
                "hand-to-shoulder",
                "hand-to-waist",
                "hand-to-head",
                "touches",
                "touch",
                "pats",
            ),
            "frame": ("frame", "connection", "connected"),
            "no contact": ("no contact", "without touching", "not touching"),
        },
    },
    "body": {
        "body part": {
            p: (p, p + "s")
            for p in (
                "arm",
                "hand",
                "leg",
                "foot",
                "head",
                "torso",
                "hip",
                "shoulder",
                "knee",
                "elbow",
                "waist",
                "chest",
                "body",
                "finger",
                "wrist",
            )
        }
        | {"foot": ("foot", "feet")},
        "action": {
            a: tuple(w for w in forms)
            for a, forms in {
                "spin": ("spin", "spins", "spinning", "twirl", "twirls"),
                "turn": ("turn", "turns", "turning", "rotate", "rotates", "rotating", "pivot"),
                "wave": ("wave", "waves", "waving"),
                "kick": ("kick", "kicks", "kicking"),
                "jump": ("jump", "jumps", "jumping", "hop", "hops", "leap"),
                "bow": ("bow", "bows", "bowing"),
                "lift": ("lift", "lifts", "raise", "raises", "raising", "lifting"),
                "lower": ("lower", "lowers", "dip", "dips", "crouch", "crouches", "squat", "bend", "bends"),
                "push / pull": ("push", "pushes", "pull", "pulls", "draws", "leads", "guides"),
                "clap": ("clap", "claps", "clapping"),
                "sway": ("sway", "sways", "swaying", "rock", "rocks", "roll", "rolls"),
                "walk / step": ("walk", "walks", "walking", "run", "runs", "step", "steps", "stepping", "stomp"),
                "copy": ("copies", "copy", "imitates", "follows", "repeats"),
                "reach": ("reach", "reaches", "extends", "stretch", "stretches", "points"),
                "punch / fight": ("punch", "punches", "strikes", "hits", "blocks", "dodges", "fight"),
            }.items()
        },
        "posture": {
            "upright": ("upright", "straight", "stands", "standing"),
            "leaning": ("lean", "leans", "leaning", "tilt", "tilts"),
            "crouched": ("crouched", "kneel", "kneels", "sits", "sitting"),
        },
    },
    "rhythm": {
        "tempo": {
            "fast": ("fast", "quick", "quickly", "rapid", "rapidly", "brisk", "energetic", "lively", "upbeat"),
            "medium": ("medium tempo", "moderate", "steady", "moderately"),
            "slow": ("slow", "slowly", "gentle", "gently", "leisurely", "calm", "calmly", "relaxed"),
        },
        "timing": {
            "on the beat": ("on the beat", "on beat", "beat", "beats", "to the music", "in time"),
            "synchronised": (
                "together",
                "in sync",
                "synchronised",
                "synchronized",
                "simultaneously",
                "in unison",
                "at the same time",
            ),
            "delayed / call-response": ("after", "later", "delay", "delayed", "in response", "responds", "echo"),
            "double time": ("double time", "half beat", "half beats", "every half"),
            "pause": ("pause", "pauses", "freeze", "freezes", "hold still", "stops"),
            "continuous": ("continuous", "continuously", "smooth", "smoothly", "flowing", "fluid"),
            "sharp": ("sharp", "staccato", "sudden", "suddenly", "abrupt"),
        },
        "stepping": {
            "basic step": ("basic step",),
            "triple step": ("triple step", "triple steps"),
            "footwork": ("footwork", "steps", "step", "stepping", "shuffle", "stomp", "feet"),
        },
        "style": {
            g: (g,)
            for g in (
                "jive",
                "swing",
                "salsa",
                "tango",
                "waltz",
                "rumba",
                "cha-cha",
                "samba",
                "lindy",
                "hip-hop",
                "ballet",
                "foxtrot",
                "bachata",
                "merengue",
            )
        },
    },
}

NOT_SPECIFIED = {
    "spatial": "The spatial relationship between the two people is not specified.",
    "body": "No specific body movement is described.",
    "rhythm": "No tempo or timing is specified.",
}


@dataclass(frozen=True)
class FocusedDescriptions:
    """The three focused descriptions of one text (app. C.2)."""

    spatial: str
    body: str
    rhythm: str

    def to_dict(self) -> dict[str, str]:
        return asdict(self)

    def as_tuple(self) -> tuple[str, str, str]:
        return self.spatial, self.body, self.rhythm


def _phrase_pattern(phrase: str) -> re.Pattern:
    words = [re.escape(w) for w in phrase.lower().split()]
    return re.compile(r"(?<![a-z0-9])" + r"[\s-]+".join(words) + r"(?![a-z0-9])")


_COMPILED: dict[str, list[tuple[str, str, re.Pattern]]] = {
    aspect: [
        (cluster, label, _phrase_pattern(p))
        for cluster, labels in clusters.items()
        for label, phrases in labels.items()
        for p in phrases
    ]
    for aspect, clusters in KEYWORD_CLUSTERS.items()
}

_CLAUSE_SPLIT = re.compile(r"(?<=[.!?;])\s+|,\s*|\s+(?:and then|then|while|whereas|as)\s+", re.IGNORECASE)


def clauses(text: str) -> list[str]:
    """The text cut at sentence ends, commas, semicolons and 'while/then/as' (stripped, non-empty)."""
    parts = (p.strip(" .;!?\t\n") for p in _CLAUSE_SPLIT.split(text.strip()))
    return [p for p in parts if p]


def find_cues(text: str) -> dict[str, dict[str, list[str]]]:
    """aspect -> cluster -> labels mentioned in ``text`` (in the order of KEYWORD_CLUSTERS)."""
    low = text.lower()
    out: dict[str, dict[str, list[str]]] = {a: {} for a in ASPECTS}
    for aspect, entries in _COMPILED.items():
        for cluster, label, pat in entries:
            if pat.search(low):
                labels = out[aspect].setdefault(cluster, [])
                if label not in labels:
                    labels.append(label)
    return out


class KeywordDecomposer:
    """Deterministic keyword-cluster decomposition (see the module docstring)."""

    name = "keywords"

    def decompose(self, text: str, genre: str | None = None) -> FocusedDescriptions:
        if not isinstance(text, str):
            raise DualFlowError(f"decompose: text must be a string, got {type(text).__name__}")
        parts = clauses(text)
        per_aspect: dict[str, list[str]] = {a: [] for a in ASPECTS}
        for clause in parts:
            cues = find_cues(clause)
            for aspect in ASPECTS:
                if cues[aspect]:
                    per_aspect[aspect].append(clause)
        all_cues = find_cues(text)
        out = {}
        for aspect in ASPECTS:
            found = all_cues[aspect]
            if not found:
                out[aspect] = NOT_SPECIFIED[aspect]
                continue
            summary = "; ".join(f"{cluster}: {', '.join(labels)}" for cluster, labels in found.items())
            body = ". ".join(c[0].upper() + c[1:] for c in per_aspect[aspect])
            out[aspect] = (body + ". " if body else "") + summary.capitalize() + "."
        return FocusedDescriptions(**out)

    def decompose_many(self, texts: Sequence[str], genre: str | None = None) -> list[FocusedDescriptions]:
        return [self.decompose(t, genre) for t in texts]


# ---------------------------------------------------------------------------------------------
# LLM backend (OpenAI-compatible chat completions), app. C.1
# ---------------------------------------------------------------------------------------------

PROMPT_VERSION = "dualflow-decompose-v1"

SYSTEM_PROMPT = (
    "You are a professional analyst of duet dance and two-person movement. Break the given description of a "
    "two-person {genre} movement into three focused descriptions: (1) spatial: the physical positioning, "
    "orientation and handholds of the two people; (2) body: the key gestures, actions and the body parts that "
    "move; (3) rhythm: tempo, timing, rhythmic style and stepping. Use only what the description says or clearly "
    'implies. Follow the reference guidelines. Answer with one JSON object with the string keys "spatial", '
    '"body" and "rhythm" and nothing else.'
)


def reference_guidelines() -> str:
    """The guideline document: per aspect, each keyword cluster with its labels (app. C.1, item 3)."""
    lines = ["Reference guidelines: typical language for each aspect of a duet motion."]
    for aspect, clusters in KEYWORD_CLUSTERS.items():
        lines.append(f"{aspect}:")
        for cluster, labels in clusters.items():
            lines.append(f"  {cluster}: {', '.join(labels)}")
    return "\n".join(lines)


#: Three worked examples per genre (ours), used as few-shot turns.
FEW_SHOT: dict[str, list[tuple[str, dict[str, str]]]] = {
    "social interaction": [
        (
            "Two people walk towards each other and shake hands, then one pats the other on the shoulder.",
            {
                "spatial": "They start apart, approach until close, face each other and join right hands; then one "
                "hand rests on the partner's shoulder.",
                "body": "Both walk forward; they extend right arms to shake hands; one raises a hand to pat the "
                "other's shoulder.",
                "rhythm": "A steady walking pace, the handshake a few short up-and-down beats, the pat brief.",
            },
        ),
        (
            "One person throws a punch and the other dodges to the left and steps back.",
            {
                "spatial": "Face to face at arm's length; the defender moves to their left and away.",
                "body": "The attacker extends an arm in a punch; the defender ducks the torso sideways and steps back.",
                "rhythm": "Fast and sudden; the dodge reacts just after the punch.",
            },
        ),
        (
            "The two hug each other warmly and sway slowly.",
            {
                "spatial": "Closed position, chest to chest, arms around each other, facing each other.",
                "body": "Arms wrap around the partner's back; the torsos sway side to side.",
                "rhythm": "Slow and continuous swaying, in unison.",
            },
        ),
    ],
    "swing": [
        (
            "The leader sends the follower out into an open position and brings her back with an underarm turn.",
            {
                "spatial": "From closed to open position with a one-hand hold, then back to closed, facing each other.",
                "body": "The leader extends the arm to send out and raises it for the follower's underarm turn.",
                "rhythm": "Lively swing tempo with triple steps, the turn on counts five and six.",
            },
        ),
        (
            "Both dancers kick forward together and clap.",
            {
                "spatial": "Side by side, no handhold.",
                "body": "Both kick a leg forward and clap their hands.",
                "rhythm": "Synchronised on the beat, sharp accents on the kicks and claps.",
            },
        ),
        (
            "The couple rock step and triple step while holding both hands.",
            {
                "spatial": "Open position facing each other with a two-hand hold.",
                "body": "Weight rocks back and forward, then small footwork with the legs and feet.",
                "rhythm": "Rock step followed by triple steps, steady swing timing.",
            },
        ),
    ],
    "latin": [
        (
            "The follower spins twice under the leader's raised right arm and ends facing him.",
            {
                "spatial": "Open position with a hand-to-hand hold through the turn, ending face to face.",
                "body": "The leader raises his right arm; the follower spins twice with arms close to the body.",
                "rhythm": "A fast double spin within one bar, finishing on the beat.",
            },
        ),
        (
            "Side by side, the partners do a cha-cha chase, mirroring each other's hip movements.",
            {
                "spatial": "Side by side and mirrored, no contact.",
                "body": "Hips sway with the steps; arms held out for balance.",
                "rhythm": "Cha-cha timing with a quick triple step, both dancers in unison.",
            },
        ),
        (
            "The leader dips the follower slowly at the end of the phrase.",
            {
                "spatial": "Closed position, the leader supporting the follower's back.",
                "body": "The follower leans back and lowers the torso; the leader bends his knees and supports her.",
                "rhythm": "Slow and held, on the last beat of the phrase.",
            },
        ),
    ],
}
DEFAULT_GENRE = "social interaction"


def build_messages(text: str, genre: str | None = None) -> list[dict[str, str]]:
    """Chat messages of app. C.1: system prompt (with genre), guidelines, 3 examples, the text."""
    g = genre if genre in FEW_SHOT else DEFAULT_GENRE
    msgs = [
        {"role": "system", "content": SYSTEM_PROMPT.format(genre=genre or g)},
        {"role": "system", "content": reference_guidelines()},
    ]
    for example, answer in FEW_SHOT[g]:
        msgs.append({"role": "user", "content": example})
        msgs.append({"role": "assistant", "content": json.dumps(answer)})
    msgs.append({"role": "user", "content": text})
    return msgs


def parse_reply(content: str, where: str) -> FocusedDescriptions:
    """The JSON object in a reply (code fences tolerated) -> FocusedDescriptions."""
    body = content.strip()
    fence = re.search(r"\{.*\}", body, re.DOTALL)
    try:
        obj = json.loads(fence.group(0) if fence else body)
    except json.JSONDecodeError as exc:
        raise DualFlowError(
            f"{where}: the LLM reply is not a JSON object ({exc}); reply was {content[:120]!r}"
        ) from exc
    missing = [k for k in ASPECTS if not isinstance(obj.get(k), str) or not obj.get(k).strip()]
    if missing:
        raise DualFlowError(f"{where}: the LLM reply lacks non-empty string field(s) {missing}")
    return FocusedDescriptions(**{k: obj[k].strip() for k in ASPECTS})


class LLMDecomposer:
    """Decomposition by an OpenAI-compatible chat endpoint, cached as JSONL (see module docstring).

    url: base URL (``…/v1``) or None -> ``$DUALFLOW_LLM_URL``; model: None -> ``$DUALFLOW_LLM_MODEL``
    (default "gpt-4o"); cache_path: JSONL file (one object per line: key, model, genre, text and
    the three descriptions), None -> no cache; timeout_s per request.
    """

    name = "llm"

    def __init__(
        self,
        url: str | None = None,
        model: str | None = None,
        cache_path: str | Path | None = None,
        timeout_s: float = 60.0,
        api_key: str | None = None,
    ):
        self.url = (url or os.environ.get("DUALFLOW_LLM_URL", "")).rstrip("/")
        if not self.url:
            raise DualFlowError(
                "decomposer 'llm': set DUALFLOW_LLM_URL to an OpenAI-compatible endpoint "
                "(e.g. http://127.0.0.1:8000/v1) or use the default 'keywords' decomposer"
            )
        if not self.url.startswith(("http://", "https://")):
            raise DualFlowError(f"DUALFLOW_LLM_URL must start with http:// or https://, got {self.url!r}")
        self.model = model or os.environ.get("DUALFLOW_LLM_MODEL", "gpt-4o")
        self.api_key = api_key if api_key is not None else os.environ.get("DUALFLOW_LLM_API_KEY")
        self.timeout_s = float(timeout_s)
        self.cache_path = Path(cache_path) if cache_path is not None else None
        self.requests = 0
        self._cache: dict[str, FocusedDescriptions] = self._read_cache()

    def key(self, text: str, genre: str | None) -> str:
        return hashlib.sha256(json.dumps([PROMPT_VERSION, self.model, genre or "", text]).encode()).hexdigest()

    def _read_cache(self) -> dict[str, FocusedDescriptions]:
        if self.cache_path is None or not self.cache_path.is_file():
            return {}
        out = {}
        lines = self.cache_path.read_text(encoding="utf-8").splitlines()
        for n, line in enumerate(lines, 1):
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
                out[rec["key"]] = FocusedDescriptions(**{k: rec[k] for k in ASPECTS})
            except (json.JSONDecodeError, KeyError, TypeError) as exc:
                if n == len(lines):  # a write cut short by a crash: the entry is simply absent
                    break
                raise DualFlowError(
                    f"{self.cache_path}:{n}: malformed decomposition cache line ({exc}); delete the line or the file"
                ) from exc
        return out

    def _append(self, key: str, text: str, genre: str | None, d: FocusedDescriptions) -> None:
        if self.cache_path is None:
            return
        self.cache_path.parent.mkdir(parents=True, exist_ok=True)
        line = json.dumps({"key": key, "model": self.model, "genre": genre, "text": text, **d.to_dict()})
        with open(self.cache_path, "a", encoding="utf-8") as f:
            f.write(line + "\n")  # one write per complete line

    def _post(self, messages: list[dict[str, str]]) -> str:
        payload = json.dumps({"model": self.model, "messages": messages, "temperature": 0}).encode()
        headers = {"Content-Type": "application/json"}
        if self.api_key:
            headers["Authorization"] = f"Bearer {self.api_key}"
        req = urllib.request.Request(self.url + "/chat/completions", data=payload, headers=headers, method="POST")
        where = f"LLM endpoint {self.url}"
        try:
            with urllib.request.urlopen(req, timeout=self.timeout_s) as resp:
                reply = json.loads(resp.read().decode("utf-8"))
        except urllib.error.HTTPError as exc:
            raise DualFlowError(f"{where}: HTTP {exc.code} {exc.reason}; check DUALFLOW_LLM_URL/MODEL/API_KEY") from exc
        except (urllib.error.URLError, OSError) as exc:
            raise DualFlowError(f"{where}: cannot connect ({exc}); check DUALFLOW_LLM_URL") from exc
        except json.JSONDecodeError as exc:
            raise DualFlowError(f"{where}: the response is not JSON ({exc})") from exc
        try:
            return reply["choices"][0]["message"]["content"]
        except (KeyError, IndexError, TypeError) as exc:
            raise DualFlowError(f"{where}: not a chat-completions response (no choices[0].message.content)") from exc

    def decompose(self, text: str, genre: str | None = None) -> FocusedDescriptions:
        if not isinstance(text, str):
            raise DualFlowError(f"decompose: text must be a string, got {type(text).__name__}")
        key = self.key(text, genre)
        if key not in self._cache:
            self.requests += 1
            d = parse_reply(self._post(build_messages(text, genre)), f"LLM endpoint {self.url}")
            self._cache[key] = d
            self._append(key, text, genre, d)
        return self._cache[key]

    def decompose_many(self, texts: Sequence[str], genre: str | None = None) -> list[FocusedDescriptions]:
        return [self.decompose(t, genre) for t in texts]


DECOMPOSERS = ("keywords", "llm")


def make_decomposer(name: str = "keywords", **kw):
    """'keywords' (default, offline) or 'llm' (needs DUALFLOW_LLM_URL; kw go to LLMDecomposer)."""
    if name == "keywords":
        return KeywordDecomposer()
    if name == "llm":
        return LLMDecomposer(**kw)
    raise DualFlowError(f"unknown decomposer {name!r}; choose one of {', '.join(DECOMPOSERS)}")
