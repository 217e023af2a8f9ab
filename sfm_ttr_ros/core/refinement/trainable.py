"""Which parameters SfM-TTR's test-time refinement trains (``refinement.trainable``).

* ``encoder``: every parameter of the encoder g, the paper's choice (Izquierdo & Civera,
  CVPR 2023, Sec. 3.3: "we only refine the encoder"), minus the first ``frozen_stages`` stages
  of a staged encoder (``frozen_encoder_levels``).
* ``norm``: only the affine weights and biases of the encoder's normalisation layers
  (LayerNorm, BatchNorm, GroupNorm, InstanceNorm, RMSNorm): a few thousand parameters.
* ``lora``: low-rank adapters (``peft`` LoRA, rank ``rank``) on the attention projections of a
  ViT encoder: query and value, and the attention output (``dense`` / ``o_proj``; fused ``qkv``
  and ``attn.proj`` for timm-style blocks), see :data:`LORA_TARGETS`. The base weights stay
  frozen; the adapters start at zero (LoRA's B = 0), so the network is unchanged until the
  first step. Convolutional encoders (ResNet, MobileNet) have no attention projections:
  ``lora`` refuses them with an :class:`InputError` (use ``encoder`` or ``norm``).
  :func:`merge_lora` folds the adapters into the base weights and removes them.

``blocks = N > 0`` (``refinement.trainable_blocks``, not in the paper) restricts any mode to
the last N transformer blocks of the encoder (:func:`encoder_blocks`): the backward pass then
stops at the first trained block instead of running down to the patch embedding, and on
Depth Anything the blocks before it run once per frame, not per step
(:func:`~sfm_ttr_ros.core.refinement.encoder.block_prefix_stages`): a ViT-S step ~2.8x cheaper than
the whole encoder with N = 4, ~3.8x with N = 2 (BENCHMARKS.md "ViT and affine paths"). Convolutional
encoders have no blocks: use ``frozen_encoder_levels`` there.

The decoder h is never trained. Only this module imports ``peft`` (lazily, for ``lora``).
"""

from __future__ import annotations

import torch
from torch import nn

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.models.base import DepthModel, ModelLoadError

TRAINABLE_MODES = ("encoder", "norm", "lora")
NORM_LAYERS = (nn.BatchNorm1d, nn.BatchNorm2d, nn.BatchNorm3d, nn.SyncBatchNorm, nn.LayerNorm,
               nn.GroupNorm, nn.InstanceNorm1d, nn.InstanceNorm2d, nn.InstanceNorm3d, nn.RMSNorm)
#: Name endings of the Linear layers LoRA adapts: query, value and output projections of HF
#: attention, in both namings (ViT / BEiT / SegFormer: ``attention.attention.query``,
#: ``attention.self.value``, ``attention.output.dense``; DINOv2 in transformers >= 5:
#: ``attention.q_proj``, ``v_proj``, ``o_proj``) and of timm-style blocks (``attn.qkv``,
#: ``attn.proj``).
LORA_TARGETS = ("query", "value", "attention.output.dense", "q_proj", "v_proj", "o_proj",
                "attn.qkv", "attn.proj")
LORA_ADAPTER = "default"
#: Names of the ModuleList that holds a transformer encoder's blocks (HF: ``encoder.layer``,
#: Llama-style ``layers``, timm ``blocks``).
BLOCK_LISTS = ("layer", "layers", "blocks")


def select_trainable(model: DepthModel, mode: str = "encoder", rank: int = 8,
                     frozen_stages: int = 0, alpha: float | None = None,
                     blocks: int = 0) -> list[nn.Parameter]:
    """The parameters that ``mode`` refines, with requires_grad on exactly them (every other
    parameter of ``model``, the decoder's included, gets requires_grad False).

    ``frozen_stages``: leading stages of a staged encoder (``stage_modules(i)``) kept fixed in
    every mode. ``mode == "lora"`` first adds adapters of rank ``rank`` (scaling
    ``alpha / rank``, alpha defaults to ``rank``) when the encoder has none: the model's module
    tree changes until :func:`merge_lora`. ``blocks`` > 0: only what
    ``mode`` selects inside the encoder's last ``blocks`` transformer blocks (LoRA adapters are
    added there only)."""
    if mode not in TRAINABLE_MODES:
        raise InputError(f"trainable must be one of {TRAINABLE_MODES}, got {mode!r}")
    encoder = model.encoder
    scope = last_blocks(encoder, blocks) if blocks else ()
    if mode == "lora" and not has_lora(model):
        add_lora(model, rank, alpha, within=scope)
    if mode == "encoder":
        chosen = list(encoder.parameters())
    elif mode == "norm":
        chosen = norm_parameters(encoder)
    else:
        chosen = lora_parameters(encoder)
    if scope:
        inside = {id(p) for name in scope for p in encoder.get_submodule(name).parameters()}
        chosen = [p for p in chosen if id(p) in inside]
    staged = model.staged_encoder
    if frozen_stages and not hasattr(staged, "stage_modules"):
        raise InputError(f"frozen_stages = {frozen_stages} needs a staged encoder; "
                         f"{type(staged).__name__} has no stage_modules: use 0")
    frozen = {id(p) for i in range(frozen_stages)
              for module in staged.stage_modules(i) for p in module.parameters()}
    params = [p for p in chosen if id(p) not in frozen]
    if not params:
        raise InputError(f"trainable {mode!r} selects no parameter of "
                         f"{type(encoder).__name__} (frozen_stages={frozen_stages})")
    for p in model.parameters():
        p.requires_grad_(False)
    for p in params:
        p.requires_grad_(True)
    return params


def check_trainable(model: DepthModel, mode: str, blocks: int = 0) -> None:
    """:class:`InputError` when ``mode`` (and ``blocks``) cannot apply to ``model``, without
    changing it (for a configuration check before any refinement runs)."""
    if mode not in TRAINABLE_MODES:
        raise InputError(f"trainable must be one of {TRAINABLE_MODES}, got {mode!r}")
    encoder = model.encoder
    scope = last_blocks(encoder, blocks) if blocks else ()
    if mode == "norm":
        norm_parameters(encoder if not scope else nn.ModuleList(
            [encoder.get_submodule(n) for n in scope]))
    elif mode == "lora" and not has_lora(model):
        if not [n for n in lora_target_names(encoder)
                if not scope or any(n.startswith(w + ".") for w in scope)]:
            raise InputError(f"trainable 'lora' needs attention projections (Linear layers "
                             f"named {', '.join(LORA_TARGETS)}) in the encoder; "
                             f"{type(encoder).__name__} has none (convolutional encoders are "
                             "not adapted): use 'encoder' or 'norm'")
        try:
            import peft  # noqa: F401
        except ImportError as exc:
            raise ModelLoadError("trainable 'lora' needs peft: pip install "
                                 "'sfm_ttr_ros[hf]'") from exc


def norm_parameters(module: nn.Module) -> list[nn.Parameter]:
    """The affine weights and biases of the normalisation layers inside ``module``."""
    params, seen = [], set()
    for m in module.modules():
        if isinstance(m, NORM_LAYERS):
            for p in m.parameters(recurse=False):
                if id(p) not in seen:
                    seen.add(id(p))
                    params.append(p)
    if not params:
        raise InputError(f"{type(module).__name__} has no normalisation layer with affine "
                         "parameters: trainable 'norm' does not apply (use 'encoder')")
    return params


def encoder_blocks(encoder: nn.Module) -> list[str]:
    """Qualified names of the encoder's transformer blocks, first to last: the entries of its
    longest ModuleList named one of :data:`BLOCK_LISTS` ([] when it has none)."""
    lists = [(n, m) for n, m in encoder.named_modules()
             if isinstance(m, nn.ModuleList) and n.rpartition(".")[2] in BLOCK_LISTS and len(m)]
    if not lists:
        return []
    name, blocks = max(lists, key=lambda item: len(item[1]))
    return [f"{name}.{i}" for i in range(len(blocks))]


def last_blocks(encoder: nn.Module, count: int) -> tuple[str, ...]:
    """The names of the encoder's last ``count`` blocks; :class:`InputError` when it has no
    transformer blocks or fewer than ``count``."""
    names = encoder_blocks(encoder)
    if int(count) < 0:
        raise InputError(f"trainable_blocks must be >= 0, got {count}")
    if not names:
        raise InputError(f"trainable_blocks = {count} needs a transformer encoder (a ModuleList "
                         f"of blocks named {', '.join(BLOCK_LISTS)}); {type(encoder).__name__} "
                         "has none: use 0 (frozen_encoder_levels restricts a staged CNN)")
    if count > len(names):
        raise InputError(f"trainable_blocks = {count} exceeds the encoder's {len(names)} blocks")
    return tuple(names[-int(count):])


def _lora_layers(module: nn.Module) -> list[tuple[str, nn.Module]]:
    return [(n, m) for n, m in module.named_modules()
            if hasattr(m, "lora_A") and hasattr(m, "get_base_layer")]


def has_lora(model: DepthModel) -> bool:
    return bool(_lora_layers(model.encoder))


def lora_parameters(module: nn.Module) -> list[nn.Parameter]:
    """The adapter weights (lora_A, lora_B) of the LoRA layers inside ``module``."""
    return [p for n, p in module.named_parameters() if ".lora_A." in n or ".lora_B." in n]


def lora_target_names(module: nn.Module, targets: tuple[str, ...] = LORA_TARGETS) -> list[str]:
    """Qualified names of the Linear layers in ``module`` whose name ends in a target."""
    return [n for n, m in module.named_modules()
            if isinstance(m, nn.Linear) and any(n == t or n.endswith("." + t) for t in targets)]


def add_lora(model: DepthModel, rank: int = 8, alpha: float | None = None,
             targets: tuple[str, ...] = LORA_TARGETS,
             within: tuple[str, ...] = ()) -> list[str]:
    """Wrap the encoder's attention projections with LoRA adapters (in place); returns the
    wrapped layers' names. ``within``: only inside these submodules (names in the encoder;
    () = anywhere). :class:`InputError` for a rank < 1, an encoder that already has adapters,
    or one without attention projections (convolutional encoders)."""
    if int(rank) < 1:
        raise InputError(f"lora rank must be >= 1, got {rank}")
    encoder = model.encoder
    if has_lora(model):
        raise InputError("the encoder already has LoRA adapters: merge_lora first")
    names = [n for n in lora_target_names(encoder, targets)
             if not within or any(n.startswith(w + ".") for w in within)]
    if not names:
        raise InputError(f"trainable 'lora' needs attention projections (Linear layers named "
                         f"{', '.join(targets)}) in the encoder; {type(encoder).__name__} has "
                         "none (convolutional encoders are not adapted): use 'encoder' or "
                         "'norm'")
    try:
        from peft import LoraConfig, inject_adapter_in_model
    except ImportError as exc:
        raise ModelLoadError("trainable 'lora' needs peft: pip install 'sfm_ttr_ros[hf]'") \
            from exc
    config = LoraConfig(r=int(rank), lora_alpha=float(alpha if alpha is not None else rank),
                        lora_dropout=0.0, target_modules=names, bias="none")
    device = next(encoder.parameters()).device
    inject_adapter_in_model(config, encoder, adapter_name=LORA_ADAPTER)
    encoder.to(device)
    return names


def merge_lora(model: DepthModel) -> int:
    """Fold every adapter into its base weight and put the plain layers back; returns the
    number of layers merged. The refined network keeps its output, the encoder its original
    module tree and state_dict keys."""
    return _unwrap(model.encoder, merge=True)


def _unwrap(encoder: nn.Module, merge: bool) -> int:
    layers = _lora_layers(encoder)
    for name, layer in layers:
        if merge:  # in place with add_ (not peft's merge(), which writes .data): the
            # weight's version counter moves, so caches keyed on it see the new weights
            with torch.no_grad():
                layer.get_base_layer().weight.add_(layer.get_delta_weight(LORA_ADAPTER))
        parent_name, _, child = name.rpartition(".")
        parent = encoder.get_submodule(parent_name) if parent_name else encoder
        setattr(parent, child, layer.get_base_layer())
    if layers and hasattr(encoder, "peft_config"):  # left by inject_adapter_in_model
        del encoder.peft_config
    return len(layers)
