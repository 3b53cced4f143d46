"""``unipixie weights fetch|status``: download the OpenCLIP weights of the CLIP feature extractor (online users) and
say which extractor a model expects and whether its weights are there."""

from __future__ import annotations

NAME = "weights"
HELP = "fetch the OpenCLIP weights the CLIP feature extractor needs, or show which extractor a model expects"
EXAMPLES = """  unipixie weights fetch                          (the weights the default model's recipe names; else ViT-B-16 laion2b_s34b_b88k)
  unipixie weights fetch --model ViT-B-16 --force
  unipixie weights fetch --checkpoint runs/clip_model   (the weights that checkpoint's features need)
  HF_ENDPOINT=https://my-mirror.example unipixie weights fetch
  unipixie weights status --checkpoint runs/clip_model"""


def add_arguments(p):
    p.add_argument("action", choices=("fetch", "status"),
                   help="fetch: download into the default weights folder (<cache>/clip/<model>/) with the Hugging Face "
                        "Hub library (progress, resumed on dropped connections, checksum verified); status: what "
                        "the model expects and what is there")
    p.add_argument("--model", metavar="NAME", help="the CLIP feature model, e.g. ViT-B-16 (default: the one the "
                                                     "checkpoint's feature recipe names)")
    p.add_argument("--checkpoint", metavar="DIR", help="the model whose features to serve (default: the shipped model)")
    p.add_argument("--folder", metavar="DIR", help="download here instead of the default weights folder (then pass it "
                                                    "as --clip-weights / the 'CLIP weights' preference)")
    p.add_argument("--force", action="store_true", help="download again even when a verified copy is there")


def _expected(checkpoint):
    """(checkpoint dir or None, the feature model it expects or None, why it could not be read)."""
    from ..errors import UserError
    from ..pipeline import model_feature_model, resolve_checkpoint

    try:
        ckpt = resolve_checkpoint(checkpoint)
        return ckpt, model_feature_model(ckpt), ""
    except UserError as exc:
        return None, None, str(exc)


def run(args) -> int:
    from .. import clip_features as cf
    from ..errors import UserError
    from ..extractors import description, needs_weights

    ckpt, expected, problem = _expected(args.checkpoint)
    if args.checkpoint and ckpt is None:
        raise UserError(problem)
    if args.action == "status":
        return _status(ckpt, expected, problem)
    model = args.model
    if not model:
        if expected and needs_weights(expected):
            model = expected
        else:
            model = cf.CLIP_MODEL
            if expected:
                print(f"note: the model in {ckpt} expects {expected!r} features ({description(expected)}, no "
                      f"weights needed); fetching {model} {cf.OPENCLIP_PRETRAINED[model]} for CLIP features "
                      "('unipixie features', 'unipixie dataset build --clip-weights', models trained on CLIP)")
    from ..weights import fetch_weights, weights_source

    src = weights_source(model)
    print(f"fetching {src.feature_model} {src.pretrained} from {src.endpoint}/{src.repo_id}")
    result = fetch_weights(model, folder=args.folder, force=args.force)
    for note in result.notes:
        print(f"warning: {note}")
    print(result.summary())
    if args.folder:
        print(f"use them with --clip-weights {result.folder} (or the add-on preference 'CLIP weights')")
    return 0


def _status(ckpt, expected, problem) -> int:
    from .. import clip_features as cf
    from ..errors import UserError
    from ..extractors import description, needs_weights

    if expected is None:
        print(f"model: {problem}")
    elif expected == cf.OFFLINE_FEATURE_MODEL:
        print(f"model {ckpt}: expects {expected} features (the offline extractor, a seeded untrained ViT: no weights "
              "needed, not CLIP)")
    elif not needs_weights(expected):
        print(f"model {ckpt}: expects {expected} features ({description(expected)}: no weights needed)")
    else:
        try:
            where = cf.resolve_clip_weights(None, model=expected)
            have = f"weights found: {where}"
        except UserError:
            have = f"no weights in {cf.default_weights_dir(expected)}: run 'unipixie weights fetch'"
        print(f"model {ckpt}: expects {expected} CLIP features; {have}")
    for model, tag in cf.OPENCLIP_PRETRAINED.items():
        folder = cf.default_weights_dir(model)
        present = folder.is_dir() and any(not p.name.startswith(".") for p in folder.iterdir())
        print(f"{model} ({tag}): {folder} {'holds weights' if present else 'is empty'}")
    return 0
