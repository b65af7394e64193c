"""MatNet checkpoints by name and shape, without PyTorch: the official
state-dict layout, the renames and drops that map a checkpoint onto it,
and what to say when they do not match. `export_matnet.py` uses it (and
checks its PyTorch module tree against `official_layout()` on every run);
`test_checkpoint.py` tests it with plain Python, so CI needs no PyTorch.

The layout is the official implementation's (github.com/lez-s/Materialist,
`Material_net/dpt.py` `MaterialNet(encoder='vitb', features=128,
out_channels=[96, 192, 384, 768])`), in its registration order; see
docs/official-matnet.md."""

DIM = 768
PATCH = 14
SIDE = 518
BLOCKS = 12
FEATURES = 128
OUT_CHANNELS = [96, 192, 384, 768]

# What a Lightning training checkpoint of the official trainer holds
# beside the network: the prefix of the network's keys, and the LPIPS
# loss network's keys (torchmetrics, AlexNet).
LIGHTNING_PREFIX = "matnet."
LOSS_PREFIX = "criterion_lpips."


def official_layout():
    """[(name, shape)] of the 303 state-dict entries, in order."""
    out = [
        ("pretrained.cls_token", (1, 1, DIM)),
        ("pretrained.pos_embed", (1, (SIDE // PATCH) ** 2 + 1, DIM)),
        ("pretrained.mask_token", (1, DIM)),
        ("pretrained.patch_embed.proj.weight", (DIM, 3, PATCH, PATCH)),
        ("pretrained.patch_embed.proj.bias", (DIM,)),
    ]
    for i in range(BLOCKS):
        b = f"pretrained.blocks.{i}."
        out += [
            (b + "norm1.weight", (DIM,)),
            (b + "norm1.bias", (DIM,)),
            (b + "attn.qkv.weight", (3 * DIM, DIM)),
            (b + "attn.qkv.bias", (3 * DIM,)),
            (b + "attn.proj.weight", (DIM, DIM)),
            (b + "attn.proj.bias", (DIM,)),
            (b + "ls1.gamma", (DIM,)),
            (b + "norm2.weight", (DIM,)),
            (b + "norm2.bias", (DIM,)),
            (b + "mlp.fc1.weight", (4 * DIM, DIM)),
            (b + "mlp.fc1.bias", (4 * DIM,)),
            (b + "mlp.fc2.weight", (DIM, 4 * DIM)),
            (b + "mlp.fc2.bias", (DIM,)),
            (b + "ls2.gamma", (DIM,)),
        ]
    out += [("pretrained.norm.weight", (DIM,)), ("pretrained.norm.bias", (DIM,))]
    for head, last in [("depth_head", 1), ("material_head", 8)]:
        h = head + "."
        c = OUT_CHANNELS
        for i, ci in enumerate(c):
            out += [(h + f"projects.{i}.weight", (ci, DIM, 1, 1)), (h + f"projects.{i}.bias", (ci,))]
        out += [
            (h + "resize_layers.0.weight", (c[0], c[0], 4, 4)),
            (h + "resize_layers.0.bias", (c[0],)),
            (h + "resize_layers.1.weight", (c[1], c[1], 2, 2)),
            (h + "resize_layers.1.bias", (c[1],)),
            (h + "resize_layers.3.weight", (c[3], c[3], 3, 3)),
            (h + "resize_layers.3.bias", (c[3],)),
        ]
        for i, ci in enumerate(c):
            out.append((h + f"scratch.layer{i + 1}_rn.weight", (FEATURES, ci, 3, 3)))
        for r in range(1, 5):
            f = h + f"scratch.refinenet{r}."
            out += [(f + "out_conv.weight", (FEATURES, FEATURES, 1, 1)), (f + "out_conv.bias", (FEATURES,))]
            for u in (1, 2):
                for k in (1, 2):
                    out += [
                        (f + f"resConfUnit{u}.conv{k}.weight", (FEATURES, FEATURES, 3, 3)),
                        (f + f"resConfUnit{u}.conv{k}.bias", (FEATURES,)),
                    ]
        out += [
            (h + "scratch.output_conv1.weight", (FEATURES // 2, FEATURES, 3, 3)),
            (h + "scratch.output_conv1.bias", (FEATURES // 2,)),
            (h + "scratch.output_conv2.0.weight", (32, FEATURES // 2, 3, 3)),
            (h + "scratch.output_conv2.0.bias", (32,)),
            (h + "scratch.output_conv2.2.weight", (last, 32, 1, 1)),
            (h + "scratch.output_conv2.2.bias", (last,)),
        ]
    return out


def parse_rename(text):
    """'OLD=NEW' -> (OLD, NEW); NEW may be empty (strip a prefix)."""
    if "=" not in text:
        raise ValueError(f"--rename {text!r}: expected OLD=NEW (NEW may be empty, as in matnet.=)")
    old, new = text.split("=", 1)
    if not old:
        raise ValueError(f"--rename {text!r}: OLD is empty")
    return old, new


def map_names(names, renames=(), drops=()):
    """Apply `drops` (prefixes, on the names as stored) and then `renames`
    ((OLD, NEW) prefix pairs, the first that matches) to `names`.
    Returns ({new name: stored name}, [errors]): a drop or rename that
    matches nothing, or two names mapped to one, is an error."""
    errors = []
    kept = []
    for p in drops:
        if not any(n.startswith(p) for n in names):
            errors.append(f"--drop {p}: no key starts with {p!r}")
    for n in names:
        if not any(n.startswith(p) for p in drops):
            kept.append(n)
    used = set()
    out = {}
    for n in kept:
        new = n
        for old, rep in renames:
            if n.startswith(old):
                new = rep + n[len(old) :]
                used.add(old)
                break
        if new in out:
            errors.append(f"{out[new]!r} and {n!r} both become {new!r}")
        out[new] = n
    for old, rep in renames:
        if old not in used:
            errors.append(f"--rename {old}={rep}: no key (left after the drops) starts with {old!r}")
    return out, errors


def compare(layout, shapes):
    """Check `shapes` ({name: shape}, after mapping) against `layout`.
    Returns [problems], each naming the key: missing, unexpected, or of
    another shape; and at the end the flags that would likely fix them."""
    want = dict(layout)
    problems = []
    missing = [n for n, _ in layout if n not in shapes]
    extra = [n for n in shapes if n not in want]
    for n in missing:
        problems.append(f"missing:    {n} {list(want[n])}")
    for n in extra:
        problems.append(f"unexpected: {n} {list(shapes[n])}")
    for n, s in layout:
        if n in shapes and tuple(shapes[n]) != tuple(s):
            problems.append(f"shape:      {n} is {list(shapes[n])}, the architecture has {list(s)}")
    hints = suggest(missing, extra)
    if hints:
        problems.append("try: " + " ".join(hints))
    return problems


def suggest(missing, extra):
    """Flags that map the usual wrappers onto the layout: the Lightning
    trainer's `matnet.` prefix and its LPIPS loss network's keys, or a
    `module.` prefix (DataParallel)."""
    out = []
    if any(n.startswith(LOSS_PREFIX) for n in extra):
        out.append(f"--drop {LOSS_PREFIX}")
    if missing:
        for p in (LIGHTNING_PREFIX, "module.", "model."):
            if any(n.startswith(p) and n[len(p) :] in missing for n in extra):
                out.append(f"--rename {p}=")
    return out
