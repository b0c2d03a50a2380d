"""``tissuecast serve MODEL``: stream predicted deformations to navigation software over OpenIGTLink.

Send marker positions (mm) as one POINT message (n_d points, model marker order) or as
TRANSFORM messages ``Marker0``..``Marker{n_d-1}``; the server answers with POLYDATA
``TissueSurface`` (deformed outer surface) and, on ``GET_POLYDATA TissueField`` or with
``--full-field``, POLYDATA ``TissueField`` (every vertex, with ``displacement_mm``).
Frames: replies are in the model's (scan's) LPS frame, or RAS with ``--client-frame RAS``
(3D Slicer's OpenIGTLinkIF); a registration TRANSFORM ``TrackerToRas``, ``ReferenceToRas``
or ``TrackerToImage`` (or ``serve.tracker_to_client`` in the config) makes the server read
markers in the tracker frame and answer in the target frame. A model trained with tracked
instruments reads each one's TRANSFORM (device ``RetractorTipToRef`` or as the config's
``[[scenario.instruments]]`` names it; tool tip = translation, push direction = third column,
mapped like the markers); when its messages stop for ``serve.instrument_timeout`` seconds the
server predicts from the markers only and says so in a STATUS. Errors come back as STRING
``ERROR``. The full protocol: docs/serving.md and the tissuecast.serve module; 3D Slicer's side
(OpenIGTLinkIF, frames): docs/label-maps.md.
"""

from __future__ import annotations

import gc
import logging
import sys

from ..config import CLIENT_FRAMES, SERVE_METHODS, TRANSFORM_MODES, ServeConfig, with_overrides
from ..errors import ConfigError
from .help_examples import with_examples

log = logging.getLogger(__name__)


#: ``--help``'s examples: (command line, what it does).
EXAMPLES = (
    ("tissuecast serve runs/quick/model",
     "listen on 127.0.0.1:18944, answer in the model's frame (LPS)"),
    ("tissuecast serve runs/quick/model --client-frame RAS --full-field",
     "for 3D Slicer's OpenIGTLinkIF (RAS), sending the whole vertex field too"),
    ("tissuecast serve runs/embedded/model --config embedded --instrument-timeout 1.0",
     "with the tracked retractor; markers only after 1 s without its TRANSFORM"),
)


def register(sub) -> None:
    p = sub.add_parser("serve", help="OpenIGTLink server streaming predicted deformations",
                       description=__doc__.split("\n\n", 1)[1].strip(), **with_examples(*EXAMPLES))
    p.add_argument("model", help="model folder written by `tissuecast train` / DeformationModel.save "
                                 "(or a SubModelSet folder: serves with one marker untracked)")
    p.add_argument("--config", help="TOML config or a packaged preset; its [serve] section gives the defaults")
    d = ServeConfig()
    p.add_argument("--host", help=f"bind address (default {d.host}: this machine only)")
    p.add_argument("--port", type=int, help=f"TCP port (default {d.port}; 0 = any free port)")
    p.add_argument("--full-field", action="store_true", default=None,
                   help="also send the full vertex field (POLYDATA TissueField) after every surface")
    p.add_argument("--transform-mode", choices=TRANSFORM_MODES,
                   help="TRANSFORM input: predict when every marker is fresh (frame) or on each update "
                        f"(default {d.transform_mode})")
    p.add_argument("--max-offset", type=float, dest="max_marker_offset",
                   help="reject markers farther than this many mm from their reference position "
                        f"(default {d.max_marker_offset:g})")
    p.add_argument("--client-frame", choices=CLIENT_FRAMES,
                   help=f"frame of replies and of markers without registration (default {d.client_frame}; LPS = the model's, "
                        "RAS for 3D Slicer)")
    p.add_argument("--method", choices=SERVE_METHODS,
                   help=f"prediction (default {d.method}): the learned model, or rigid registration of the markers "
                        "(the navigation systems' baseline, a fallback)")
    p.add_argument("--instrument-timeout", type=float, dest="instrument_timeout",
                   help=f"seconds without an instrument's TRANSFORM before predicting from the markers only "
                        f"(default {d.instrument_timeout:g})")
    p.add_argument("--parameter", action="append", metavar="NAME=VALUE",
                   help="a measured parameter the model reads (scenario.uncertain.measured): a factor on the nominal value "
                   "for youngs_modulus, spring_* and density (1 = nominal), the ratio itself for poisson_ratio, mm for "
                   "attached_margin; e.g. youngs_modulus=1.3")
    p.add_argument("--no-uncertainty", action="store_true", help="do not send ensemble uncertainty")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..serve import IGTLServer, SurfacePredictor
    from ..serve.status import ALARM_NAME, REFUSED_NAME, STATUS_DEVICE
    from ..surrogate.robust import load_model_folder
    from ..app.configuration import load_run_config

    cfg = load_run_config(args.config)
    overrides = {k: getattr(args, k) for k in ("host", "full_field", "transform_mode", "max_marker_offset", "client_frame",
                                                 "method", "instrument_timeout")
                 if getattr(args, k) is not None}
    if args.port is not None and not 0 <= args.port <= 65535:
        raise ConfigError(f"--port {args.port}: give 0 (any free port) or a TCP port 1-65535")
    if args.port:  # 0 (any free port) is allowed here but not in a config file
        overrides["port"] = args.port
    serve = with_overrides(cfg, serve=overrides).serve
    port = 0 if args.port == 0 else serve.port
    model = load_model_folder(args.model)  # a DeformationModel or a SubModelSet folder
    from .predict_inputs import parse_parameters

    devices = {i.name: i.device for i in cfg.scenario.instruments if i.name in {x.name for x in model.auxiliary.instruments}}
    predictor = SurfacePredictor(model, max_marker_offset=serve.max_marker_offset,
                                 use_uncertainty=not args.no_uncertainty, method=serve.method, devices=devices,
                                 parameters=parse_parameters(args.parameter))
    try:
        server = IGTLServer.from_config(predictor, serve, port=port)
    except OSError as exc:  # address in use, unknown host, no permission for ports < 1024
        raise ConfigError(f"cannot listen on {serve.host}:{port}: {exc}; choose another --port or --host") from exc
    host, port = server.address
    n_d = predictor.n_markers
    print(f"serving {args.model} on {host}:{port} (OpenIGTLink)", flush=True)
    print(f"  input : POINT (any device name, {n_d} points, mm, model marker order) or "
          f"TRANSFORM Marker0..Marker{n_d - 1} ({serve.transform_mode} mode); registration: TRANSFORM "
          "TrackerToRas / ReferenceToRas / TrackerToImage", flush=True)
    print(f"  frames: {server.frames.describe()}", flush=True)
    for device, name in predictor.instrument_devices.items():
        print(f"  instrument {name!r}: TRANSFORM {device} (tool tip, push direction = third column); markers only "
              f"after {serve.instrument_timeout:g} s without it (STATUS InstrumentLost)", flush=True)
    if serve.method != "mlp":
        print(f"  method: {serve.method} (the learned model is not used)", flush=True)
    print(f"  output: POLYDATA TissueSurface ({len(predictor.surface_ids)} points, "
          f"{len(model.mesh.surface_triangles)} triangles"
          f"{', uncertainty_mm' if predictor.has_uncertainty else ''}"
          f"{', error_bound_mm' if predictor.has_bounds else ''}); GET_POLYDATA TissueField -> "
          f"POLYDATA TissueField ({predictor.n_vertices} points{', every prediction' if serve.full_field else ''}); "
          "errors: STRING ERROR", flush=True)
    alarm = (f"after the mesh {ALARM_NAME} while the alarm is raised, OK once it clears; " if predictor.has_bounds
             else "")
    print(f"  status: STATUS {STATUS_DEVICE}: {alarm}{REFUSED_NAME} (no mesh) for marker input no simulation could "
          "produce", flush=True)
    print("press Ctrl+C to stop", file=sys.stderr, flush=True)
    # the model and the server live as long as this process: the garbage collector's full
    # passes need not walk them between frames (they set the latency's tail)
    gc.collect()
    gc.freeze()
    try:
        server.serve_forever()
    finally:
        server.stop()
    return 0
