"""MCAP episode logs: one zstd-compressed ``.mcap`` file per evaluated episode, Foxglove-ready.

Every message is JSON with a JSON-schema, so the file opens in Foxglove (which reads JSON +
jsonschema channels, and recognises its *well-known* schemas by name) and in any MCAP reader.

==================  =========================  =================================================
topic               schema                     content (one message per env step unless said)
==================  =========================  =================================================
``/scene``          ``foxglove.SceneUpdate``   once, at the start: the object's primitives and
                                               the hand's collision capsules/boxes, each entity
                                               frame-locked to its body's frame
``/tf``             ``foxglove.FrameTransforms``  the poses: ``world`` -> every hand body
                                               (``hand/<body>``; ``hand/forearm`` is the hand
                                               base), the palm centre (``palm_center``) and the
                                               object (``object``)
``/joint_states``   ``foxglove.JointStates``   the 30 joints, 6 base (ARTx..ARRz: the observed
                                               hand pose) + 24 hand: angle (position) and
                                               servo force (effort: the joint torque observed)
``/command``        ``forcegrasp.Command``     the policy's action (7), the 30 commanded servo
                                               targets (base targets first) and commanded h
``/reward``         ``forcegrasp.RewardTerms``  reward and its terms r_a r_b r_c, h, object
                                               displacement, palm error, return so far,
                                               success, failure
``/outcome``        ``forcegrasp.EpisodeOutcome``  once, at the end: return, length, success,
                                               failure, seed, placement offset
==================  =========================  =================================================

Message times are sim time: the episode's wall-clock start plus ``step * dt`` (dt = frame_skip x
timestep = 20 ms), so Foxglove plays an episode back at real speed. Step 0 (the reset state) is
logged too: an episode of ``n`` steps has ``n + 1`` messages on the per-step topics.

The MCAP metadata record ``forcegrasp.episode`` holds what a replay needs to rebuild the scene
(object, mass scale, ...) plus the checkpoint and placement of the episode.

Files are written to a temporary name and renamed when the episode ends: a crash never leaves a
truncated ``.mcap`` under the final name.
"""


from forcegrasp.mcap_log.logger import EpisodeLogger
from forcegrasp.mcap_log.messages import FLOAT_WIDTH, fixed_chars
from forcegrasp.mcap_log.reader import EpisodeLog, read_episode
from forcegrasp.mcap_log.schemas import METADATA_NAME, ONCE_TOPICS, PER_STEP_TOPICS, SCHEMAS, TOPIC_SCHEMAS

__all__ = ["FLOAT_WIDTH", "METADATA_NAME", "ONCE_TOPICS", "PER_STEP_TOPICS", "SCHEMAS", "TOPIC_SCHEMAS", "EpisodeLog",
           "EpisodeLogger", "fixed_chars", "read_episode"]
