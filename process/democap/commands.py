"""``mocaprig democap ...``: train and evaluate the DeMoCap markers-to-pose network.

Registered through the ``mocaprig.commands`` entry point ``democap``. Handlers import torch
and the pipeline lazily so ``mocaprig --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mocaprig.cli import add_json_flag, emit_json, usage_handler
from mocaprig.progress import ProgressBar, StageProgress, StatusLine

__all__ = [
    "PROTOCOL_CHOICES",
    "VARIANT_CHOICES",
    "democap_eval",
    "democap_live",
    "democap_run",
    "democap_subject",
    "democap_train",
    "register_democap",
]

_EPILOG = """\
examples:
  mocaprig democap train --config lite --out lite.pt --epochs 40
  mocaprig democap train --out lite.pt --epochs 80 --resume     continue a run
  mocaprig democap eval --json                                  committed lite checkpoint
  mocaprig democap eval --protocol unseen-real --json           the headline: real motion
  mocaprig democap eval --protocol all --json                   every protocol, labelled
  mocaprig democap eval --cameras 2 --seed 3
  mocaprig democap eval --motion walk.bvh --json                a motion never trained on
  mocaprig democap run session.mcap --calib calib.toml --out results.mcap   replay a recording
  mocaprig democap subject rom.mcap --calib calib.toml --out actor.json   calibrate the actor
  mocaprig democap run session.mcap --calib calib.toml --out r.mcap --subject actor.json
  mocaprig democap live --calib calib.toml --out live.mcap          live from the D415 rig
  mocaprig democap train --variant pose --out pose.pt --epochs 4   a baseline (docs/democap.md)
"""

#: ``DemocapConfig.variant`` values (spelled out here: importing the config would import
#: torch through the package, and ``mocaprig --help`` must stay fast).
VARIANT_CHOICES = ("markers-to-pose", "pose", "markers+pose", "regression")
#: ``evaluate.PROTOCOLS``, spelled out for the same reason (a test checks they agree).
PROTOCOL_CHOICES = (
    "in-distribution",
    "unseen-real",
    "off-model",
    "leave-one-activity-out",
    "perturbed",
)

_TRAIN_EPILOG = """\
Training data is simulated on the fly (marker-level D415 model, see docs/democap.md) and is
deterministic for --seed. A checkpoint is written after every epoch; --resume continues it.

examples:
  mocaprig democap train --config lite --out lite.pt --epochs 40 --threads 2
  mocaprig democap train --out lite.pt --epochs 80 --resume
  mocaprig democap train --config lite --out lite.pt --overwrite --max-minutes 30
  mocaprig democap train --variant markers+pose --out mp.pt --epochs 4 --threads 1
  mocaprig democap train --config lite --out mine.pt --bvh walk.bvh dance.bvh --epochs 40
  mocaprig democap train --config paper --out paper.pt --epochs 60 --device cuda --data-workers 12
  mocaprig democap train --out loao.pt --hold-out-activity dance --epochs 40
  mocaprig democap train --out lite.pt --resume --epochs 260 --lr 2.5e-4   # fine-tune on the corpus
  mocaprig democap train --out sim-only.pt --no-corpus --epochs 40

--corpus DIR (default: ../shared/data/motion/corpus when present; --no-corpus: none) adds the
motion corpus's train split (process/democap/data/corpus_split.toml, split by CMU subject) to
the pool, each clip centred on the rig and retargeted onto --corpus-subjects training bodies;
the validation split becomes a second validation set (val_corpus_mpjpe_mm). --hold-out-activity
A leaves activity A's clips out (a leave-one-activity-out run). --bvh adds other motion-capture
clips (retargeted onto --bvh-subjects bodies each; a third of the procedural takes are already
random key poses). The checkpoint keeps the clips' names, and `democap eval` flags a clip that
was trained on.

--variant picks the network of a new run: markers-to-pose (DeMoCap, the default) or one of the
baselines of paper Table 2 (pose: joint heat maps only; markers+pose: both super-stages
predict markers and joints) or a direct-regression network (regression). A resumed run keeps
its checkpoint's variant.
"""

_EVAL_EPILOG = """\
--protocol picks what is held out (docs/democap.md, "Protocols"):
  in-distribution          held-out simulated takes: new bodies and takes, but training's
                           actions, body sampler and D415 model (the default)
  unseen-real              the motion corpus's test split: real motion of performers never
                           trained on (the headline); clips the checkpoint trained on are
                           flagged and left out
  off-model                the unseen-real clips on subjects the body model does not mirror
                           (proportions x2, marker placement x2.5, 1.5 cm skin motion)
  leave-one-activity-out   per activity, its corpus clips not trained on; says whether the
                           activity itself was trained on
  perturbed                in-distribution takes with the D415 model's detection rate, noise,
                           stray points and occlusion at 0.5x and 1.5x training's, then on
                           subjects pushed off the body model
  all                      all five
--motion FILE.bvh (a BVH retargeted onto new subjects) and --freestyle (held-out random key
poses) replace the protocol. Every figure is given over all frames and over the frames with
the actor inside the volume the cameras see (with that share), and by the true torso's tilt
from the vertical (0-20, 20-40, 40-60 and past 60 degrees: a body bent over is the hard case);
frames whose cloud has fewer than 2 points are skipped and counted. --frames is per take or
clip (default per protocol: 40, 20, 10, 8), --subjects the bodies per clip (corpus) or rounds
of the actions.
The estimates are skeleton solves by default: the body model (pose, segment lengths, girth)
fitted to the cloud from the network's estimates, the ensemble's and each turn's, the best fit
kept; --no-solve scores the network's own estimates (the paper's output). With
--subject-calibration N each take's frames (one subject) are solved, the subject's segment
lengths and marker placement calibrated from them, and solved again, N times (one more solve
per round; 0, the default, solves every frame on its own).
MPJPE is over the paper's 17 joints (no toes), MPMPE over the 53 markers, in mm. Any variant's
checkpoint can be evaluated; a pose baseline estimates no markers, so its MPMPE, RMSPMPE and
MPJAE are reported as n/a (null with --json).

examples:
  mocaprig democap eval
  mocaprig democap eval --protocol unseen-real --subjects 2 --json
  mocaprig democap eval --protocol all --frames 8 --json
  mocaprig democap eval --ckpt lite.pt --cameras 4 --json
  mocaprig democap eval --all-cameras --json        4-, 3- and 2-camera figures
  mocaprig democap eval --motion ../shared/data/motion/cmu_131_02_scaled.bvh
  mocaprig democap eval --freestyle --json          random key poses never trained on
  mocaprig democap eval --protocol unseen-real --no-solve --rotations 1   the paper's single shot
  mocaprig democap eval --protocol off-model --subject-calibration 1 --json
"""

_RUN_EPILOG = """\
Every D415 frame's device time is mapped onto the calibration's reference clock (Vicon) with
that camera's clock mapping; frames within a quarter frame period form one rig instant (an
instant seen by fewer cameras is still processed). Per instant: IR blobs + depth -> camera
points -> world (calibration poses) -> capture-box crop -> 10 mm merge -> the network -> the
skeleton solve (the body model fitted to the cloud; --no-solve keeps the network's estimates).

Outputs (none is replaced without --overwrite):
  results.mcap  Foxglove SceneUpdate on /democap/markers, /democap/joints (bones + names) and
                /democap/cloud (the fused input), log_time = reference time (ns)
  results.c3d   53 markers then the 19 joints as J_<joint>, mm (--c3d; default: beside --out)
  results.csv   time_s (reference clock), then <name>_x,<name>_y,<name>_z in mm (--csv)

examples:
  mocaprig democap run sim/session.mcap --calib calib.toml --out results.mcap
  mocaprig democap run sim/session.mcap --calib calib.toml --out r.mcap --every 3 --json
  mocaprig democap run s.mcap --calib calib.toml --out r.mcap --c3d r_pose.c3d --csv r.csv
  mocaprig democap run s.mcap --calib calib.toml --out r.mcap --ckpt lite.pt --overwrite
  mocaprig democap run s.mcap --calib calib.toml --out r.mcap --subject actor.json
"""

_SUBJECT_EPILOG = """\
What a marker-based system does with a range-of-motion trial: the actor's segment lengths,
girth and where each marker sits on its segment, measured from a recording of them (one actor
in view). --instants instants spread evenly over the recording go through the replay's
pipeline; each cloud is solved on its own, the subject is calibrated from the half the solve
explains best (medians), and every cloud is solved again with it (--rounds times). The
subject file (JSON: standing height, scale, girth, segment lengths in m, marker offsets in mm
in each segment's frame) is then given to `democap run --subject` or `democap live --solve
--subject`: every instant is solved as that body instead of sampling it frame by frame.

examples:
  mocaprig democap subject rom.mcap --calib calib.toml --out actor.json
  mocaprig democap subject rom.mcap --calib calib.toml --out actor.json --instants 80 --json
  mocaprig democap subject take.mcap --calib calib.toml --out actor.json --end 0.8
      from the take's first 0.8 s (a T-pose at the start)
  mocaprig democap run take.mcap --calib calib.toml --out take_results.mcap --subject actor.json
"""


def register_democap(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``democap`` and its sub-commands to the ``mocaprig`` parser."""
    dm = subparsers.add_parser(
        "democap",
        help="DeMoCap: marker clouds -> labelled markers + joints (train, evaluate)",
        description="DeMoCap markers-to-pose network: train it and evaluate it on simulated data.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = dm.add_subparsers(dest="democap_command", metavar="SUBCOMMAND")
    dm.set_defaults(func=usage_handler(dm))

    tr = sub.add_parser(
        "train",
        help="train a network on simulated D415 marker data",
        description="Train (or resume) a DeMoCap network on simulated data.",
        epilog=_TRAIN_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    tr.add_argument("--config", choices=("lite", "paper"), default="lite", help="network size")
    tr.add_argument(
        "--variant",
        choices=VARIANT_CHOICES,
        default=None,
        help="network variant of a new run (default: markers-to-pose)",
    )
    tr.add_argument("--out", required=True, metavar="CKPT", help="checkpoint file to write")
    tr.add_argument("--epochs", type=int, default=40, help="train until this many epochs")
    tr.add_argument("--resume", action="store_true", help="continue the run stored in --out")
    tr.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    tr.add_argument("--seed", type=int, default=0, help="seed of a new run")
    tr.add_argument("--takes", type=int, default=96, help="training takes (subjects x motions)")
    tr.add_argument("--samples-per-epoch", type=int, default=None, help="override the config")
    tr.add_argument("--batch-size", type=int, default=None, help="override the config")
    tr.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    tr.add_argument(
        "--device",
        choices=("auto", "cpu", "cuda"),
        default="auto",
        help="where the network trains (auto: a CUDA GPU when torch sees one, with mixed "
        "precision; else the CPU)",
    )
    tr.add_argument(
        "--data-workers",
        type=int,
        default=0,
        metavar="N",
        help="processes simulating training batches ahead (0: in the training process; a GPU "
        "wants several). The batches do not depend on N",
    )
    tr.add_argument("--max-minutes", type=float, default=None, help="stop after this wall time")
    tr.add_argument(
        "--observation-jitter",
        type=float,
        default=0.0,
        metavar="J",
        help="each sample's D415 model scales (detection, noise, strays, occlusion) drawn from "
        "[1-J, 1+J] (default: 0, the nominal model); the perturbed protocol's 0.5x / 1.5x "
        "should stay outside it",
    )
    tr.add_argument(
        "--lr",
        type=float,
        default=None,
        help="learning rate from this run's first epoch (default: the config's, or the resumed "
        "run's schedule); with --resume a warm restart, the decay continuing from it",
    )
    tr.add_argument(
        "--bvh",
        nargs="+",
        default=(),
        metavar="FILE.bvh",
        help="BVH clips added to the training pool (a resumed run needs the same ones)",
    )
    tr.add_argument("--bvh-subjects", type=int, default=4, help="bodies per BVH clip")
    tr.add_argument(
        "--joint-map",
        type=Path,
        default=None,
        metavar="FILE.toml",
        help='our joint -> BVH joint for the --bvh skeletons, lines like LeftUpLeg = "Thigh_L"',
    )
    tr.add_argument(
        "--corpus",
        type=Path,
        default=None,
        metavar="DIR",
        help="motion corpus folder: its train split joins the pool "
        "(default: ../shared/data/motion/corpus when present)",
    )
    tr.add_argument("--no-corpus", action="store_true", help="train without the motion corpus")
    tr.add_argument("--corpus-subjects", type=int, default=2, help="bodies per corpus clip")
    tr.add_argument(
        "--hold-out-activity",
        action="append",
        default=[],
        metavar="ACTIVITY",
        help="leave this activity's corpus clips out of training (repeatable)",
    )
    add_json_flag(tr)
    tr.set_defaults(func=democap_train)

    ev = sub.add_parser(
        "eval",
        help="measure a checkpoint on a held-out simulated test set",
        description="Evaluate a checkpoint on held-out simulated sessions with known truth.",
        epilog=_EVAL_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ev.add_argument("--ckpt", default=None, help="checkpoint (default: the committed lite one)")
    ev.add_argument(
        "--protocol",
        choices=(*PROTOCOL_CHOICES, "all"),
        default="in-distribution",
        help="what is held out (default: %(default)s; see below)",
    )
    ev.add_argument(
        "--corpus",
        type=Path,
        default=None,
        metavar="DIR",
        help="motion corpus folder (default: ../shared/data/motion/corpus when present)",
    )
    ev.add_argument("--motion", default=None, metavar="FILE.bvh", help="test on this BVH motion")
    ev.add_argument(
        "--joint-map",
        type=Path,
        default=None,
        metavar="FILE.toml",
        help='our joint -> BVH joint for --motion, lines like LeftUpLeg = "Thigh_L"',
    )
    ev.add_argument(
        "--freestyle",
        action="store_true",
        help="test on held-out random key poses instead of the scored actions",
    )
    ev.add_argument("--seed", type=int, default=0, help="seed of the test set")
    ev.add_argument("--cameras", type=int, choices=(2, 3, 4), default=4, help="D415s used")
    ev.add_argument("--all-cameras", action="store_true", help="report 4, 3 and 2 cameras")
    ev.add_argument("--subjects", type=int, default=1, help="subjects (rounds of the actions)")
    ev.add_argument(
        "--frames", type=int, default=None, help="frames per take or clip (default per protocol)"
    )
    ev.add_argument(
        "--threads", type=int, default=1, help="torch CPU threads (default: %(default)s)"
    )
    ev.add_argument(
        "--subject-calibration",
        type=int,
        default=0,
        metavar="N",
        help="calibrate each take's subject from its frames and solve again, N rounds "
        "(default: %(default)s = every frame on its own)",
    )
    _add_inference_options(ev)
    add_json_flag(ev)
    ev.set_defaults(func=democap_eval)

    rn = sub.add_parser(
        "run",
        help="replay a recording: D415 markers -> labelled markers + joints (MCAP, C3D, CSV)",
        description="Replay the D415 streams of a recording through DeMoCap.",
        epilog=_RUN_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    rn.add_argument("session", metavar="SESSION.mcap", type=Path, help="the recording")
    rn.add_argument(
        "--calib", type=Path, required=True, metavar="CALIB", help="calibration (.toml or .json)"
    )
    rn.add_argument("--out", type=Path, required=True, metavar="OUT.mcap", help="results MCAP")
    rn.add_argument("--c3d", type=Path, default=None, metavar="OUT.c3d", help="C3D output")
    rn.add_argument("--csv", type=Path, default=None, metavar="OUT.csv", help="CSV output")
    rn.add_argument("--ckpt", default=None, help="checkpoint (default: the committed lite one)")
    rn.add_argument("--every", type=int, default=1, metavar="N", help="every N-th instant")
    rn.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    rn.add_argument("--no-crop", action="store_true", help="keep points outside the capture box")
    rn.add_argument(
        "--threads", type=int, default=1, help="torch CPU threads (default: %(default)s)"
    )
    _add_inference_options(rn)
    _add_subject_option(rn, "every instant is solved as this subject")
    add_json_flag(rn)
    rn.set_defaults(func=democap_run)

    sj = sub.add_parser(
        "subject",
        help="calibrate the actor of a recording (segment lengths, marker placement) into a "
        "subject file for run/live",
        description="Calibrate a recording's actor into a subject file (JSON).",
        epilog=_SUBJECT_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sj.add_argument("session", metavar="SESSION.mcap", type=Path, help="a recording of the actor")
    sj.add_argument(
        "--calib", type=Path, required=True, metavar="CALIB", help="calibration (.toml or .json)"
    )
    sj.add_argument(
        "--out", type=Path, required=True, metavar="SUBJECT.json", help="subject file to write"
    )
    sj.add_argument(
        "--instants",
        type=int,
        default=40,
        metavar="N",
        help="instants to calibrate from, spread over the recording (default: %(default)s)",
    )
    sj.add_argument(
        "--rounds", type=int, default=1, help="calibration rounds (default: %(default)s)"
    )
    sj.add_argument(
        "--start",
        type=float,
        default=None,
        metavar="S",
        help="use the recording from S seconds after its first instant (its range-of-motion "
        "or static part; default: from the start)",
    )
    sj.add_argument(
        "--end",
        type=float,
        default=None,
        metavar="S",
        help="... up to S seconds after its first instant (default: to the end)",
    )
    sj.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    sj.add_argument("--ckpt", default=None, help="checkpoint (default: the committed lite one)")
    sj.add_argument("--no-crop", action="store_true", help="keep points outside the capture box")
    sj.add_argument(
        "--threads", type=int, default=1, help="torch CPU threads (default: %(default)s)"
    )
    add_json_flag(sj)
    sj.set_defaults(func=democap_subject)

    lv = sub.add_parser(
        "live",
        help="live DeMoCap from the D415 rig (or --mock): joints at the camera rate, recorded",
        description="Run DeMoCap live on the D415 rig and record the results.",
        epilog=_LIVE_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    lv.add_argument(
        "--calib", type=Path, required=True, metavar="CALIB", help="calibration (.toml or .json)"
    )
    lv.add_argument("--seconds", type=float, default=10.0, help="capture length (default 10)")
    lv.add_argument("--out", type=Path, default=None, metavar="OUT.mcap", help="results MCAP")
    lv.add_argument("--mock", action="store_true", help="the simulated rig instead of USB")
    lv.add_argument("--seed", type=int, default=0, help="--mock: world seed (default 0)")
    lv.add_argument("--scenario", default="default", help="--mock: scenario (default: default)")
    lv.add_argument(
        "--world-seconds",
        type=float,
        default=10.0,
        metavar="S",
        help="--mock: length of the simulated session the calibration comes from (the world "
        "depends on it; default 10, the demo's)",
    )
    lv.add_argument("--ckpt", default=None, help="checkpoint (default: the committed lite one)")
    lv.add_argument(
        "--threads", type=int, default=1, help="torch CPU threads (default: %(default)s)"
    )
    lv.add_argument(
        "--rotations",
        type=int,
        default=2,
        metavar="K",
        help="rotation ensemble size (default: %(default)s, the live setting; 1 = single shot)",
    )
    lv.add_argument(
        "--solve",
        action="store_true",
        help="fit the body model to each cloud (as the replay does; ~10x the network's time "
        "on a CPU, so off by default live)",
    )
    lv.add_argument(
        "--no-pose-bank",
        action="store_true",
        help="with --solve: start it from the network's estimates only, not also from the "
        "committed bank of real poses",
    )
    lv.add_argument(
        "--no-pose-prior",
        action="store_true",
        help="with --solve: solve without the committed prior over joint angles of real motion",
    )
    lv.add_argument(
        "--no-compile",
        action="store_true",
        help="run the network uncompiled (by default it is compiled with torch.compile when "
        "the cameras start, 10-30 s once, then about a quarter faster a pass)",
    )
    _add_resolve_option(lv)
    _add_subject_option(lv, "with --solve: every instant is solved as this subject")
    add_json_flag(lv)
    lv.set_defaults(func=democap_live)

    pb = sub.add_parser(
        "pose-bank",
        help="build the skeleton solve's bank of real poses from the corpus's train split",
        description="Build the pose bank (k-means medoids of the train split's poses) that the "
        "skeleton solve also starts from.",
        epilog=_BANK_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _add_train_split_artifact_args(pb, "bank")
    pb.add_argument("--size", type=int, default=256, help="poses (default: %(default)s)")
    pb.add_argument(
        "--rate",
        type=float,
        default=10.0,
        metavar="HZ",
        help="frames per second of each clip clustered (default: %(default)s)",
    )
    pb.set_defaults(func=democap_pose_bank)

    pp = sub.add_parser(
        "pose-prior",
        help="build the skeleton solve's prior over joint angles from the corpus's train split",
        description="Build the pose prior (a Gaussian mixture over the 27 joint angles of the "
        "train split's poses) that every skeleton solve holds.",
        epilog=_PRIOR_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _add_train_split_artifact_args(pp, "prior")
    pp.add_argument("--components", type=int, default=8, help="Gaussians (default: %(default)s)")
    pp.add_argument(
        "--rate",
        type=float,
        default=30.0,
        metavar="HZ",
        help="frames per second of each clip used (default: %(default)s)",
    )
    pp.add_argument(
        "--floor",
        type=float,
        default=5.0,
        metavar="DEG",
        help="standard deviation added to every angle's spread (default: %(default)s)",
    )
    pp.set_defaults(func=democap_pose_prior)


def _add_train_split_artifact_args(parser: argparse.ArgumentParser, noun: str) -> None:
    """The options of a command that builds a file from the corpus's train split."""
    parser.add_argument(
        "--out", type=Path, required=True, metavar="OUT.npz", help=f"the {noun} file"
    )
    parser.add_argument(
        "--corpus",
        type=Path,
        default=None,
        metavar="DIR",
        help="corpus folder (default: ../shared/data/motion/corpus beside the repository)",
    )
    parser.add_argument("--seed", type=int, default=0, help="k-means seed (default: %(default)s)")
    parser.add_argument("--overwrite", action="store_true", help=f"replace an existing {noun} file")
    add_json_flag(parser)


_BANK_EPILOG = """\
Every clip of the corpus's train split (process/democap/data/corpus_split.toml) is retargeted
onto the 1.75 m reference body at --rate Hz, its heading removed, and the frames clustered by
their joint positions; each cluster's medoid (a real frame) is a pose of the bank. The
committed bank (process/democap/data/pose_bank.npz) is the default of this command.

examples:
  mocaprig democap pose-bank --out process/democap/data/pose_bank.npz --overwrite
  mocaprig democap pose-bank --corpus ~/cmu --size 128 --out bank128.npz --json
"""


_PRIOR_EPILOG = """\
Every clip of the corpus's train split (process/democap/data/corpus_split.toml) is retargeted
onto the 1.75 m reference body at --rate Hz and the frames' joint angles clustered (k-means);
each cluster gives a Gaussian (its mean, its covariance with --floor degrees added to every
spread). The committed prior (process/democap/data/pose_prior.npz) is the default of this
command.

examples:
  mocaprig democap pose-prior --out process/democap/data/pose_prior.npz --overwrite
  mocaprig democap pose-prior --corpus ~/cmu --components 4 --out prior4.npz --json
"""


_LIVE_EPILOG = """\
The D415s are configured (the first found is the sync master, the others slaves) and started;
their frame sets are grouped into rig instants on the calibration's reference clock (the
replay's rule) and run through the same pipeline as `democap run`: IR blobs + depth -> world ->
10 mm merge -> the network (2-turn rotation ensemble by default, the live setting, compiled
for this CPU before the cameras start: 10-30 s, once; --no-compile skips it). A status
line on stderr shows the rate, the cameras per instant and the latency. Results go into --out
through the recorder (SceneUpdate on /democap/markers and /democap/joints; drops counted).
When the network is slower than the cameras (--solve) the oldest waiting instant is skipped
for the newest, so the joints stay current; each skip is counted and logged in the file.

With --mock the cameras are the simulated rig (seed --seed, scenario --scenario): use the
calibration of a simulated session of the same seed and length, e.g. `mocaprig demo` (seed 0,
10 s: demo-out/calib.toml). The simulated cameras render their images on this CPU, which bounds
the rate.

examples:
  mocaprig democap live --calib calib.toml --seconds 60 --out take1.mcap
  mocaprig democap live --mock --calib demo-out/calib.toml --seconds 3 --json
"""


def _add_inference_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--rotations",
        type=int,
        default=3,
        metavar="K",
        help="rotation ensemble size: the cloud turned by k*180/K deg about the vertical, "
        "K network passes, median (default: %(default)s; 1 = the paper's single shot)",
    )
    parser.add_argument(
        "--no-solve",
        action="store_true",
        help="the network's estimates as they are, without fitting the body model to the "
        "cloud (the paper's output; the solve is the default)",
    )
    parser.add_argument(
        "--no-pose-bank",
        action="store_true",
        help="the solve starts from the network's estimates only, not also from the committed "
        "bank of real poses (faster; worse where the network is far off)",
    )
    parser.add_argument(
        "--no-pose-prior",
        action="store_true",
        help="the solve holds no prior over joint angles (the committed Gaussian mixture of "
        "real motion's angles; worse where the cloud says little about a limb)",
    )
    _add_resolve_option(parser)


def _check_threads(args: argparse.Namespace) -> None:
    """``--threads`` is at least 1."""
    if args.threads < 1:
        from mocaprig.errors import ValidationError

        msg = f"--threads must be >= 1, got {args.threads}"
        raise ValidationError(msg)


def _add_subject_option(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument(
        "--subject",
        type=Path,
        default=None,
        metavar="SUBJECT.json",
        help=f"a subject file (`democap subject`): {what}, its segment lengths and marker "
        "placement held (default: every instant on its own)",
    )


def _subject(args: argparse.Namespace, *, solves: bool) -> Any:
    """The ``--subject`` file read, or None; refused without the solve."""
    if args.subject is None:
        return None
    from mocaprig.errors import ValidationError
    from mocaprig.process.democap.subject import load_subject

    if not solves:
        msg = "--subject is used by the skeleton solve; drop --no-solve (or give --solve live)"
        raise ValidationError(msg)
    return load_subject(args.subject)


def _add_resolve_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--resolve-rounds",
        type=int,
        default=2,
        metavar="N",
        help="with the solve: a cloud still explained poorly is solved again from its own "
        "solution, up to N times (default: %(default)s; 0 = never)",
    )


def democap_train(args: argparse.Namespace) -> int:
    """Handler of ``mocaprig democap train``; returns 0.

    Raises:
        ValidationError: ``--variant`` with ``--resume`` names another variant than the
            checkpoint's.
    """
    import dataclasses

    from mocaprig.errors import ValidationError
    from mocaprig.process.body.bvh import load_joint_map, read_bvh
    from mocaprig.process.democap.checkpoint import load_checkpoint
    from mocaprig.process.democap.config import config_by_name
    from mocaprig.process.democap.train import TrainOptions, train

    if args.resume and args.variant is not None:
        stored = load_checkpoint(Path(args.out)).config.variant
        if stored != args.variant:
            msg = (
                f"{args.out} is a {stored!r} run; --variant applies to new runs only "
                "(leave it out to resume, or train a new run with --overwrite)"
            )
            raise ValidationError(msg)
    config = config_by_name(args.config)
    if args.variant is not None:
        config = dataclasses.replace(config, variant=args.variant)
    joint_map = None if args.joint_map is None else load_joint_map(args.joint_map)
    motions = tuple(read_bvh(p, joint_map=joint_map) for p in args.bvh)
    corpus, validation = _train_corpus(args)

    opts = TrainOptions(
        epochs=args.epochs,
        seed=args.seed,
        takes=args.takes,
        samples_per_epoch=args.samples_per_epoch,
        batch_size=args.batch_size,
        threads=args.threads,
        device=args.device,
        data_workers=args.data_workers,
        max_seconds=None if args.max_minutes is None else 60.0 * args.max_minutes,
        motions=motions,
        motion_subjects=args.bvh_subjects,
        corpus=corpus,
        corpus_subjects=args.corpus_subjects,
        validation_motions=validation,
        lr=args.lr,
        observation_jitter=args.observation_jitter,
    )
    bar = ProgressBar("democap train", unit="steps")
    ckpt = train(
        Path(args.out),
        opts,
        config=config,
        resume=args.resume,
        overwrite=args.overwrite,
        progress=bar,
    )
    bar.finish()
    last = ckpt.history[-1] if ckpt.history else {}
    summary: dict[str, Any] = {
        "checkpoint": str(args.out),
        "config": ckpt.config.name,
        "variant": ckpt.config.variant,
        "epochs": ckpt.epoch,
        "loss": last.get("loss"),
        "val_mpjpe_mm": last.get("val_mpjpe_mm"),
        "val_corpus_mpjpe_mm": last.get("val_corpus_mpjpe_mm"),
        "corpus_clips": [c.name for c in corpus],
        "validation_clips": [c.name for c in validation],
        "train_motions": ckpt.train_motions,
    }
    if args.json:
        emit_json(summary)
    else:
        print(
            f"{args.out}: {ckpt.config.name} {ckpt.config.variant}, {ckpt.epoch} epochs, "
            f"loss {summary['loss']}, "
            f"held-out MPJPE {summary['val_mpjpe_mm']} mm"
        )
    return 0


def democap_pose_bank(args: argparse.Namespace) -> int:
    """Handler of ``mocaprig democap pose-bank``; returns 0.

    Raises:
        ValidationError: no corpus folder, a missing clip, or a bad size or rate.
        RecordingError: the output exists without ``--overwrite``.
    """
    from mocaprig.process.democap.pose_bank import build_pose_bank, save_pose_bank

    clips = _train_split_clips(args)
    bank = build_pose_bank(clips, size=args.size, rate_hz=args.rate, seed=args.seed)
    save_pose_bank(bank, args.out, overwrite=args.overwrite)
    summary = {"out": str(args.out), "poses": len(bank), "clips": len(bank.source)}
    if args.json:
        emit_json(summary)
    else:
        print(f"{len(bank)} poses from {len(bank.source)} clips -> {args.out}")
    return 0


def democap_pose_prior(args: argparse.Namespace) -> int:
    """Handler of ``mocaprig democap pose-prior``; returns 0.

    Raises:
        ValidationError: no corpus folder, a missing clip, or a bad count, rate or floor.
        RecordingError: the output exists without ``--overwrite``.
    """
    from mocaprig.process.democap.pose_prior import build_pose_prior, save_pose_prior

    clips = _train_split_clips(args)
    prior = build_pose_prior(
        clips,
        components=args.components,
        rate_hz=args.rate,
        floor_deg=args.floor,
        seed=args.seed,
    )
    save_pose_prior(prior, args.out, overwrite=args.overwrite)
    summary = {"out": str(args.out), "components": len(prior), "clips": len(prior.source)}
    if args.json:
        emit_json(summary)
    else:
        print(f"{len(prior)} components from {len(prior.source)} clips -> {args.out}")
    return 0


def _train_split_clips(args: argparse.Namespace) -> list[Any]:
    """The corpus's train split clips for a command that writes ``--out`` from them.

    Raises:
        ValidationError: no corpus folder, or a missing clip.
        RecordingError: ``--out`` exists without ``--overwrite`` (checked before the reading).
    """
    from mocaprig.errors import RecordingError, ValidationError
    from mocaprig.process.democap.corpus import load_split, read_corpus_clips

    corpus = _corpus_dir(args.corpus)
    if corpus is None:
        msg = (
            "no motion corpus beside the repository (../shared/data/motion/corpus); "
            "pass --corpus DIR"
        )
        raise ValidationError(msg)
    if Path(args.out).exists() and not args.overwrite:
        msg = f"{args.out} exists; pass --overwrite to replace it"
        raise RecordingError(msg)
    return list(read_corpus_clips(corpus, load_split().in_split("train")))


def _corpus_dir(arg: Path | None) -> Path | None:
    from mocaprig.process.democap.corpus import default_corpus_dir

    return arg if arg is not None else default_corpus_dir()


def _train_corpus(args: argparse.Namespace) -> tuple[tuple[Any, ...], tuple[Any, ...]]:
    """The corpus train clips (minus held-out activities) and validation clips for
    ``democap train``; none with ``--no-corpus`` or when there is no corpus folder.

    Raises:
        ValidationError: ``--corpus`` with ``--no-corpus``, an unknown activity, or a
            missing clip.
    """
    from mocaprig.errors import ValidationError
    from mocaprig.process.democap.corpus import load_split, read_corpus_clips

    if args.no_corpus and args.corpus is not None:
        msg = "pass either --corpus DIR or --no-corpus, not both"
        raise ValidationError(msg)
    table = load_split()
    unknown = sorted(set(args.hold_out_activity) - set(table.activities()))
    if unknown:
        msg = f"unknown activities {unknown}; the split table has {', '.join(table.activities())}"
        raise ValidationError(msg)
    folder = None if args.no_corpus else _corpus_dir(args.corpus)
    if folder is None:
        if not args.no_corpus:
            print("no motion corpus folder: training without it (--corpus DIR)", file=sys.stderr)
        return (), ()
    keep = [c for c in table.in_split("train") if c.activity not in args.hold_out_activity]
    return (
        tuple(read_corpus_clips(folder, keep)),
        tuple(read_corpus_clips(folder, table.in_split("validation"))),
    )


def _figure_progress(
    progress: StageProgress, protocol: str, cameras: int, *, several: bool
) -> Callable[[str, int, int], None]:
    """``progress`` with each figure named by its protocol (and cameras when several)."""

    def report(label: str, done: int, total: int) -> None:
        name = label if label == protocol else f"{protocol} {label}"
        progress(f"{name}, {cameras} cameras" if several else name, done, total)

    return report


def democap_eval(args: argparse.Namespace) -> int:
    """Handler of ``mocaprig democap eval``; returns 0.

    Raises:
        ValidationError: ``--motion`` or ``--freestyle`` with a ``--protocol`` other than the
            default, ``--all-cameras`` with a protocol of several figures, or a corpus
            protocol without a corpus folder.
    """
    from mocaprig.errors import ValidationError
    from mocaprig.process.body.bvh import load_joint_map, read_bvh
    from mocaprig.process.democap.evaluate import (
        PROTOCOLS,
        ProtocolResult,
        evaluate,
        held_out_pool,
        run_protocol,
    )
    from mocaprig.process.democap.infer import DemocapPredictor

    special = args.motion is not None or args.freestyle
    if special and args.protocol != "in-distribution":
        msg = "--motion and --freestyle replace --protocol; pass one of them"
        raise ValidationError(msg)
    _check_threads(args)
    import torch

    torch.set_num_threads(args.threads)
    if args.subject_calibration < 0 or (args.subject_calibration and args.no_solve):
        msg = "--subject-calibration takes N >= 0 rounds and needs the solve (not --no-solve)"
        raise ValidationError(msg)
    protocols = PROTOCOLS if args.protocol == "all" else (args.protocol,)
    single = special or args.protocol in ("in-distribution", "unseen-real", "off-model")
    if args.all_cameras and not single:
        msg = f"--all-cameras applies to one figure; protocol {args.protocol!r} gives several"
        raise ValidationError(msg)
    predictor = DemocapPredictor(
        None if args.ckpt is None else Path(args.ckpt),
        rotations=args.rotations,
        solve=not args.no_solve,
        pose_bank=not args.no_pose_bank,
        pose_prior=not args.no_pose_prior,
        resolve_rounds=args.resolve_rounds,
        subject_calibration=args.subject_calibration,
    )
    cams = (4, 3, 2) if args.all_cameras else (args.cameras,)
    corpus = _corpus_dir(args.corpus)
    # One line per figure: its frames as they are estimated (the solve takes minutes).
    progress = StageProgress("democap eval: ")
    seen = False
    results: list[ProtocolResult] = []
    by_cameras: dict[str, Any] = {}
    if special:
        joint_map = None if args.joint_map is None else load_joint_map(args.joint_map)
        clip = None if args.motion is None else read_bvh(args.motion, joint_map=joint_map)
        if clip is not None and clip.name in predictor.checkpoint.train_motions:
            seen = True
            print(
                f"warning: {args.motion} (clip {clip.name!r}) was in this checkpoint's "
                "training pool; the figures are not held out",
                file=sys.stderr,
            )
        frames = args.frames or 40
        pool = held_out_pool(
            args.seed, motion=clip, subjects=args.subjects, freestyle=args.freestyle
        )
        for k in cams:
            rep = evaluate(
                predictor,
                seed=args.seed,
                num_cameras=k,
                frames_per_take=frames,
                pool=pool,
                progress=progress.stage(f"{k} cameras"),
            )
            res = ProtocolResult(
                "bvh-motion" if clip is not None else "freestyle",
                "bvh-motion" if clip is not None else "freestyle",
                f"the motion of {args.motion}, on new bodies"
                if clip is not None
                else "random key poses of the test stream (training draws other keys)",
                rep,
                trained_on=seen,
                budget={"frames_per_take": frames, "subjects": args.subjects, "seed": args.seed},
            )
            results.append(res)
            by_cameras[str(k)] = res.to_dict()
        results = results[:1]
    else:
        for proto in protocols:
            for k in cams:
                got = run_protocol(
                    predictor,
                    proto,
                    corpus_dir=corpus,
                    seed=args.seed,
                    num_cameras=k,
                    subjects=args.subjects,
                    frames=args.frames,
                    progress=_figure_progress(progress, proto, k, several=len(cams) > 1),
                )
                if k == cams[0]:
                    results += got
                by_cameras[str(k)] = got[0].to_dict()
    progress.done()
    for r in results:
        if r.trained_clips:
            print(
                f"warning: {r.protocol} {r.label}: clip(s) {', '.join(r.trained_clips)} were "
                "trained on; left out of the figure",
                file=sys.stderr,
            )
    out: dict[str, Any] = {
        "checkpoint": str(args.ckpt or "committed lite"),
        "config": predictor.checkpoint.config.name,
        "variant": predictor.checkpoint.config.variant,
        "protocol": args.protocol if not special else results[0].protocol,
        "motion": args.motion
        or ("freestyle (held-out)" if args.freestyle else "procedural (held-out)"),
        "motion_trained_on": seen,
        "rotations": predictor.rotations,
        "solve": predictor.solves,
        # the ensemble a sparse cloud's solve starts from (None: never another)
        "sparse_rotations": predictor.sparse_rotations if predictor.solves else None,
        "sparse_points": predictor.sparse_points,
        # poses in the bank the solve also starts from (None: the network's starts only)
        "pose_bank_poses": None if predictor.pose_bank is None else len(predictor.pose_bank),
        "pose_prior_components": (
            None if predictor.pose_prior is None else len(predictor.pose_prior)
        ),
        # rounds of the re-solve from the solve's own solution (0: never)
        "resolve_rounds": predictor.resolve_rounds if predictor.solves else 0,
        "seed": args.seed,
        "corpus": None if corpus is None else str(corpus),
        "trained_corpus_clips": sorted(predictor.checkpoint.train_motions),
    }
    if len(results) == 1 and results[0].report is not None:
        out.update(results[0].to_dict())
    out["protocol"] = args.protocol if not special else results[0].protocol
    out["results"] = [r.to_dict() for r in results]
    if len(cams) > 1:
        out["by_cameras"] = by_cameras
    if args.json:
        emit_json(out)
        return 0
    if not predictor.predicts_markers:
        print(f"{out['variant']} baseline: no markers, so no MPMPE and no MPJAE")
    if len(cams) > 1:
        for k, r in by_cameras.items():
            print(_result_line(f"{k} cameras", r))
        return 0
    for res in results:
        print(_result_line(f"{cams[0]} cameras", res.to_dict()))
    return 0


def _result_line(prefix: str, r: dict[str, Any]) -> str:
    """One protocol figure as text."""
    head = f"{r['protocol']}" + ("" if r["label"] == r["protocol"] else f" [{r['label']}]")
    if "mpjpe_mm" not in r:
        return f"{head}: no figure ({r['note']})"
    ins = r["inside_volume"]
    inside = (
        "no frame inside the volume"
        if ins["mpjpe_mm"] is None
        else f"inside the volume ({100 * ins['share']:.0f} % of frames): MPJPE "
        f"{ins['mpjpe_mm']:.1f} mm, PCK@50 {100 * ins['pck50']:.1f} %"
    )
    flag = " (trained on)" if r["trained_on"] else ""
    first = (
        f"{head}{flag}, {prefix}: MPJPE {r['mpjpe_mm']:.1f} mm, RMSPJPE {r['rmspjpe_mm']:.1f} mm, "
        f"MPMPE {_fmt(r['mpmpe_mm'], ' mm')}, PCK@50 {100 * r['pck50']:.1f} %, "
        f"MPJAE {_fmt(r['mpjae_deg'], ' deg')} ({r['frames']} frames, "
        f"{r['skipped_frames']} skipped); {inside}"
    )
    lines = [first, f"  holds out: {r['holds_out']}"]
    if r["note"]:
        lines.append(f"  note: {r['note']}")
    acts = ", ".join(f"{a} {v:.1f}" for a, v in r["per_action_mm"].items())
    lines.append(f"  per action or clip (mm): {acts}")
    tilts = ins.get("per_torso_tilt") or {}
    if tilts:
        bins = ", ".join(
            f"{k} deg {_fmt(v['mpjpe_mm'], ' mm')} ({v['frames']})" for k, v in tilts.items()
        )
        lines.append(f"  inside, by the torso's tilt from the vertical (frames): {bins}")
    return "\n".join(lines)


def _fmt(value: float | None, unit: str) -> str:
    return "n/a" if value is None else f"{value:.1f}{unit}"


def democap_run(args: argparse.Namespace) -> int:
    """Handler of ``mocaprig democap run``; returns 0."""
    import torch

    from mocaprig.process.democap.infer import DemocapPredictor
    from mocaprig.process.democap.replay import DEFAULT_CROP_BOX_M, run_replay

    _check_threads(args)
    subject = _subject(args, solves=not args.no_solve)
    torch.set_num_threads(args.threads)
    bar = ProgressBar("democap run", unit="instants")
    result = run_replay(
        args.session,
        args.calib,
        out=args.out,
        c3d=args.c3d,
        csv=args.csv,
        predictor=DemocapPredictor(
            None if args.ckpt is None else Path(args.ckpt),
            rotations=args.rotations,
            solve=not args.no_solve,
            pose_bank=not args.no_pose_bank,
            pose_prior=not args.no_pose_prior,
            resolve_rounds=args.resolve_rounds,
            subject=subject,
        ),
        every=args.every,
        overwrite=args.overwrite,
        crop_box_m=None if args.no_crop else DEFAULT_CROP_BOX_M,
        progress=bar,
    )
    bar.finish()
    summary = result.summary()
    if args.json:
        emit_json(summary)
        return 0
    hist = ", ".join(f"{v} with {k}" for k, v in sorted(result.camera_histogram.items()))
    print(
        f"{args.session}: {result.instants} instants ({hist} cameras; "
        f"{result.skipped_instants} skipped), {result.mean_points:.1f} points per cloud, "
        f"{summary['seconds']:.1f} s ({result.checkpoint})"
    )
    for kind, path in result.outputs.items():
        print(f"  {kind:<4} -> {path}")
    return 0


def democap_subject(args: argparse.Namespace) -> int:
    """Handler of ``mocaprig democap subject``; returns 0."""
    import torch

    from mocaprig.process.democap.infer import DemocapPredictor
    from mocaprig.process.democap.replay import DEFAULT_CROP_BOX_M, fit_subject
    from mocaprig.process.democap.subject import check_subject_path, save_subject

    _check_threads(args)
    out = check_subject_path(args.out, overwrite=args.overwrite)
    torch.set_num_threads(args.threads)
    bar = ProgressBar("democap subject", unit="instants")
    fit = fit_subject(
        args.session,
        args.calib,
        instants=args.instants,
        rounds=args.rounds,
        start_s=args.start,
        end_s=args.end,
        predictor=DemocapPredictor(None if args.ckpt is None else Path(args.ckpt)),
        crop_box_m=None if args.no_crop else DEFAULT_CROP_BOX_M,
        progress=bar,
    )
    bar.finish()
    n = int(fit.t_ref_ns.size)
    save_subject(
        fit.subject,
        out,
        source=f"{args.session}: {n} of {fit.instants_total} instants",
        overwrite=args.overwrite,
    )
    summary = {**fit.summary(), "out": str(out)}
    if args.json:
        emit_json(summary)
        return 0
    spread = summary["frame_by_frame_height_m"]
    print(
        f"{args.session}: subject of standing height {fit.subject.standing_height_m:.3f} m "
        f"from {n} instants ({fit.skipped_instants} skipped; frame by frame "
        f"{spread['p10']:.3f}-{spread['p90']:.3f} m), {fit.seconds:.1f} s"
    )
    print(f"  subject -> {out}")
    return 0


class _LiveStatus:
    """``democap live``'s figures on the :class:`~mocaprig.progress.StatusLine`."""

    def __init__(self, *, enabled: bool) -> None:
        self._line = StatusLine(enabled=enabled)
        self._t0 = time.monotonic()
        self._n = 0
        self._skipped = 0

    def __call__(self, res: Any, inst: Any) -> None:
        self._n += 1
        self._skipped += bool(res.skipped)
        if res.skipped or not self._line.due():
            return
        elapsed = time.monotonic() - self._t0
        seen = sum(f is not None for f in inst.frames.values())
        self._line.show(
            f"live {elapsed:6.1f} s  {self._n} instants  {self._n / max(elapsed, 1e-9):5.1f} /s  "
            f"cameras {seen}/{len(inst.frames)}  points {res.points:3d}  "
            f"latency {res.timings_ms['latency_ms']:4.0f} ms  skipped {self._skipped}"
        )

    def close(self) -> None:
        self._line.done()


def democap_live(args: argparse.Namespace) -> int:
    """Handler of ``mocaprig democap live``; returns 0 (130 when interrupted)."""
    import threading

    import torch

    from mocaprig.acquire.camera_backends import open_cameras
    from mocaprig.calib.calibration import read_calibration
    from mocaprig.errors import ValidationError
    from mocaprig.process.democap.infer import DemocapPredictor
    from mocaprig.process.democap.live_capture import run_live

    _check_threads(args)
    subject = _subject(args, solves=args.solve)
    calibration = read_calibration(args.calib)
    torch.set_num_threads(args.threads)
    predictor = DemocapPredictor(
        None if args.ckpt is None else Path(args.ckpt),
        rotations=args.rotations,
        solve=args.solve,
        pose_bank=not args.no_pose_bank,
        pose_prior=not args.no_pose_prior,
        resolve_rounds=args.resolve_rounds,
        compile=not args.no_compile,
        subject=subject,
    )
    if args.mock and args.seconds > args.world_seconds:
        msg = f"--seconds {args.seconds} exceeds the simulated session (--world-seconds)"
        raise ValidationError(msg)
    if args.mock:
        cameras = open_cameras(
            "mock", scenario=args.scenario, seed=args.seed, seconds=args.world_seconds
        )
    else:
        cameras = open_cameras("realsense")
    status = _LiveStatus(enabled=not args.json)
    stop = threading.Event()
    try:
        summary = run_live(
            cameras,
            calibration,
            seconds=args.seconds,
            out=args.out,
            predictor=predictor,
            on_result=status,
            stop=stop,
        )
    except KeyboardInterrupt:
        stop.set()
        status.close()
        print("interrupted; the results file is finished", file=sys.stderr)
        return 130
    finally:
        for cam in cameras:
            cam.close()
    status.close()
    if args.json:
        emit_json(summary.as_dict())
        return 0
    lat = "n/a" if summary.latency_ms_p50 is None else f"{summary.latency_ms_p50:.0f} ms"
    print(
        f"{len(summary.cameras)} cameras, {summary.instants} instants in {summary.wall_s:.1f} s "
        f"({summary.fps:.1f} /s), {summary.predicted} with joints, latency p50 {lat}"
    )
    if summary.skipped:
        print(f"  {summary.skipped} instants skipped: the network was behind the cameras")
    if summary.compiled:
        print(f"  network compiled before the start ({summary.warm_up_s:.1f} s)")
    if summary.out is not None:
        print(f"  mcap -> {summary.out} ({summary.drops} dropped)")
    return 0
