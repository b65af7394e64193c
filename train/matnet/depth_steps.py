#!/usr/bin/env python3
"""Where models' depth jumps, against where the truth's does.

For each held-out sample of a decoded `rooms` dataset (the
`decoded.npz` train.py writes beside it), each model's predicted depth
has a step at a pixel where |log z| changes by more than --tau to its
right or lower neighbour (the truth's likewise); pixels within 2 px of
invalid ones are left out. Prints, per model, medians over the samples
(per kind and over all): the share of the frame the predicted steps
cover, the share covered by steps with no true step within 2 px
("false"), and the share of true steps with a predicted one within 2 px
(recall). False steps are what a relight shows as sparkling slivers.

The photo goes in as the dataset stores it (256², sRGB to linear by
^2.2), not through matflow's 512² round trip: a diagnostic to compare
models with, not the bench's numbers (`matflow-bench matnet`).

    python3 train/matnet/depth_steps.py out/matnet/heldout/decoded.npz \\
        models/matnet_rooms.onnx CANDIDATE.onnx ...
"""
import argparse

import numpy as np


def steps(logz, tau):
    """Pixels whose log depth differs by more than tau from their right
    or lower neighbour."""
    s = np.zeros(logz.shape, bool)
    s[:, :-1] |= np.abs(logz[:, 1:] - logz[:, :-1]) > tau
    s[:-1] |= np.abs(logz[1:] - logz[:-1]) > tau
    return s


def dilate(mask, r):
    """mask grown by r pixels (a (2r+1)² square)."""
    h, w = mask.shape
    p = np.pad(mask, r)
    out = np.zeros_like(mask)
    for dy in range(2 * r + 1):
        for dx in range(2 * r + 1):
            out |= p[dy:dy + h, dx:dx + w]
    return out


def measure(pred, true, valid, tau=0.05, reach=2):
    """(share of the frame in predicted steps, share in predicted steps
    with no true step within `reach` px, share of true steps with a
    predicted one within `reach` px) for depth maps `pred` and `true`;
    pixels within `reach` px of invalid ones are left out."""
    keep = ~dilate(~valid, reach)
    sp = steps(np.log(np.maximum(pred, 1e-4)), tau) & keep
    st = steps(np.log(np.maximum(true, 1e-4)), tau) & keep
    false = sp & ~dilate(st, reach)
    found = st & dilate(sp, reach)
    return sp.mean(), false.mean(), found.sum() / max(st.sum(), 1)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("decoded", help="a dataset's decoded.npz (train.py writes it)")
    ap.add_argument("models", nargs="+", help="MatNet-contract ONNX models")
    ap.add_argument("--tau", type=float, default=0.05, help="a step: |log z| changes by more than this")
    a = ap.parse_args()
    import onnxruntime as ort

    d = np.load(a.decoded)
    photo, depth, valid, kind = d["photo"], d["depth"], d["valid"], d["kind"]
    print("| model | predicted steps | false steps (closed / open / outdoor / stage) | recall |")
    print("|---|---|---|---|")
    for m in a.models:
        sess = ort.InferenceSession(m, providers=["CPUExecutionProvider"])
        names = [o.name for o in sess.get_outputs()]
        rows = []
        for i in range(len(photo)):
            x = ((photo[i].astype(np.float32) / 255.0) ** 2.2).transpose(2, 0, 1)[None]
            out = dict(zip(names, sess.run(None, {sess.get_inputs()[0].name: x})))
            rows.append((kind[i], *measure(out["depth"][0, 0], depth[i], valid[i], a.tau)))
        med = lambda j, k=None: np.median([r[j] for r in rows if k is None or r[0] == k])
        per = " / ".join(f"{100 * med(2, k):.1f}" for k in ("closed", "open", "outdoor", "stage"))
        print(f"| {m} | {100 * med(1):.1f} % | {100 * med(2):.1f} % ({per}) | {med(3):.2f} |")


if __name__ == "__main__":
    main()
