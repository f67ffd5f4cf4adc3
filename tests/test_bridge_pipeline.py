"""The partner pipeline: actor source → DualFlow reactor → streaming retarget → control loop.

Real parts throughout: a real (tiny, untrained) DualFlow checkpoint on disk, the bundled
op3 model's CasADi retargeter, the bridge's limits from the op3 hardware config, and the
record-only transport (dry run).
"""

import numpy as np
import pytest
import torch

from dualflow.checkpoint import save_checkpoint
from dualflow.model import DualFlow, DualFlowConfig
from dualflow.motion.features import encode_pair
from dualflow.motion.normalization import NormStats
from dualflow.streaming import StreamConfig
from dualflow.synthetic import make_duet, make_leader
from ros_free_bridge.control.loop import ControlLoop, LoopConfig
from ros_free_bridge.control.targets import TargetBuffer
from ros_free_bridge.partner.pipeline import PartnerPipeline
from ros_free_bridge.partner.reactor import Cues, ReactorStage
from ros_free_bridge.partner.retarget_stage import RetargetStage
from ros_free_bridge.robots import bridge_limits, resolve_robot
from ros_free_bridge.sources.replay import MotionReplaySource
from ros_free_bridge.transports.record import RecordTransport

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def op3():
    from retarget.robot import load_robot

    files = resolve_robot("op3")
    limits = bridge_limits(files.hardware_config())
    return load_robot(files.mjcf, files.profile), limits


def _run(op3, reactor, seconds=1.5):
    robot, limits = op3
    retarget = RetargetStage(robot, 30.0, limits.names)
    buf = TargetBuffer(30.0)
    tr = RecordTransport(limits.names, initial=limits.clip(np.zeros(limits.n)))
    loop = ControlLoop(tr, limits, buf, LoopConfig(handle_signals=False, min_ramp=0.3, rest_after=30.0))
    leader = make_leader(seconds, 30.0, seed=2)
    pipe = PartnerPipeline(MotionReplaySource(leader), reactor, retarget, buf, loop.ready)
    pipe.start()
    summary = loop.run()
    pipe.join(5)
    cmds = np.asarray(tr.commands)
    assert np.all(cmds >= limits.lower - 1e-9) and np.all(cmds <= limits.upper + 1e-9)
    assert np.all(np.abs(np.diff(cmds, axis=0)) <= limits.max_velocity * 0.01 + 1e-9)
    return summary, pipe, leader


def test_generated_partner_streams_every_frame_to_the_transport(op3, tiny_checkpoint):
    reactor = ReactorStage(30.0, tiny_checkpoint, StreamConfig(window=16, steps=2))
    summary, pipe, leader = _run(op3, reactor)
    assert summary.end_state == "STOPPED" and summary.reason == "the motion ended"
    assert pipe.frames_in == leader.n_frames
    # one partner frame per actor frame: the newest actor row is encoded with a predicted next
    # frame (ReactorStage(predict_next=True)), so the last frame has a row too
    assert pipe.frames_out == leader.n_frames
    # nearly every frame is played: a late tick, or frames that arrive in a burst after the
    # playback clock has passed them, make the loop jump to the newest (it keeps time)
    assert 0.8 * pipe.frames_out <= summary.frames_played <= pipe.frames_out + pipe.settle_frames


def test_imitation_retargets_the_actor_itself(op3):
    summary, pipe, leader = _run(op3, None)
    assert summary.end_state == "STOPPED"
    assert pipe.frames_out == pipe.frames_in == leader.n_frames


def test_the_stream_ends_with_the_robot_stepping_back_to_its_stance(op3):
    """After the last actor frame the core sends the robot's return to its stance: targets
    flagged ``settle``, on the same frame timeline, without an arrival (no latency is counted
    for them), in small batches, then a ``settle`` event; the last one is the stand pose,
    which is the loop's rest pose, so the stop ramp after it has little to do."""
    from ros_free_bridge.partner.core import PartnerCore
    from ros_free_bridge.sources.udp import ActorFrame

    robot, limits = op3
    core = PartnerCore(None, RetargetStage(robot, 30.0, limits.names))
    leader = make_leader(3.0, 30.0, seed=2)
    out = []
    for k in range(leader.n_frames):
        out += core.feed([ActorFrame(k, leader.positions[k], k / 30.0)])[0]
    batches = list(core.finish_stream())
    settle = [t for targets, _ in batches for t in targets]
    events = [e for _, ev in batches for e in ev]
    assert len(out) == leader.n_frames and not any(t.settle for t in out)
    assert len(settle) >= 15 and all(t.settle and np.isnan(t.arrival) for t in settle)
    assert [t.index for t in out + settle] == list(range(len(out) + len(settle)))
    assert max(len(targets) for targets, _ in batches) <= PartnerCore.SETTLE_BATCH
    assert [e["kind"] for e in events] == ["settle"] and events[0]["frames"] == len(settle)
    stand = np.asarray(robot.x_stand)[robot.n_root :]
    rest = limits.clip(stand[[robot.joint_names.index(n) for n in limits.names]])
    assert np.abs(settle[-1].q - rest).max() < 0.1 < np.abs(out[-1].q - rest).max()


def test_text_and_music_reach_the_generator(tmp_path):
    import soundfile as sf

    torch.manual_seed(0)
    feats, _ = encode_pair(make_duet("follow", 4.0, 30.0, 0))
    ckpt = tmp_path / "tiny_cond"
    model = DualFlow(DualFlowConfig.preset("tiny"))
    with torch.no_grad():  # the condition paths start at zero (adaLN-zero); wake them up
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
    save_checkpoint(
        ckpt,
        model=model,
        stats=NormStats.from_features(feats),
        meta={"text_encoder": "hashed_bag_of_words_v1/dim384/seed0", "music": "edge35"},
    )
    sr = 22050
    clicks = np.zeros(sr * 2, np.float32)
    for b in np.arange(0.25, 2.0, 0.5):  # 120 bpm
        clicks[int(b * sr) : int(b * sr) + 200] = 0.8
    sf.write(tmp_path / "clicks.wav", clicks, sr)
    leader = make_leader(1.0, 30.0, seed=5)

    def stream(**cond):
        stage = ReactorStage(30.0, ckpt, StreamConfig(window=16, steps=2), Cues(music_frames=100, **cond))
        out = []
        for k in range(leader.n_frames):
            out += stage.push(leader.positions[k], 0.0, k)
        return stage, np.stack([f.positions for f in out])

    stage, with_cond = stream(text="the partner follows the leader", music=tmp_path / "clicks.wav")
    assert tuple(stage.streamer.cond.text.shape) == (1, 384)
    assert tuple(stage.streamer.cond.music.shape) == (1, 100, 35)  # 2 s track (60 frames) looped to 100
    _, plain = stream()
    assert np.abs(with_cond - plain).max() > 1e-4  # the conditions change what is generated


def test_a_model_without_music_refuses_a_music_file(tiny_checkpoint, tmp_path):
    from ros_free_bridge.errors import BridgeError

    with pytest.raises(BridgeError, match="without music"):
        ReactorStage(30.0, tiny_checkpoint, StreamConfig(window=16, steps=2), Cues(music=tmp_path / "x.wav"))
