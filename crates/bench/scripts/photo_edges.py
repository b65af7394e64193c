#!/usr/bin/env python3
"""How well the photo's own edges alone hold a click to its object.

The edit's `mask_object` grows a region over the predictions and stops
where the photo steps by more than `object_edges` (γ-encoded 3×3 means).
This measures that edge rule alone, with no predictions, on the
held-out generated scenes, three ways:

- adjacent: the step between the two neighbours' means (matflow's rule):
  a soft or anti-aliased outline steps by a third of its contrast there;
- across: from the pixel before the pair to the one beyond (tried and
  reverted: texture and render noise step as much across three pixels,
  see docs/notes/2026-11-matnet-kinds.md);
- pixels: no pixel whose own central difference exceeds the step.

True objects: each connected region of one true albedo without a depth
step (ln z by > 0.1), 0.5-30 % of the image; the click at its most
interior pixel. Without the rings that add an outline's own pixels, so
recall is a little low for all three.

  python3 crates/bench/scripts/photo_edges.py [--heldout out/matnet/heldout]

Needs numpy and scipy, and the held-out set decoded by train.py."""
import argparse
import os

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

def comps(Hok, Vok, h, w):
    """Connected components of the pixel grid over the allowed horizontal
    (Hok) and vertical (Vok) neighbour pairs."""
    idx=np.arange(h*w).reshape(h,w)
    r=np.concatenate([idx[:,:-1][Hok],idx[:-1,:][Vok]]); c=np.concatenate([idx[:,1:][Hok],idx[1:,:][Vok]])
    g=coo_matrix((np.ones(len(r)),(r,c)),shape=(h*w,h*w))
    return connected_components(g,directed=False)[1].reshape(h,w)

def sh(a, dy, dx):
    """a[y + dy, x + dx], clamped to the image."""
    h,w=a.shape[:2]; ys=np.clip(np.arange(h)+dy,0,h-1); xs=np.clip(np.arange(w)+dx,0,w-1)
    return a[ys][:,xs]

def rules(s, step):
    """Each rule's connected regions over the 3x3 means s."""
    h,w,_=s.shape; out={}
    # adjacent means
    out['adjacent']=comps(np.abs(s[:,1:]-s[:,:-1]).max(-1)<=step, np.abs(s[1:]-s[:-1]).max(-1)<=step,h,w)
    # across: pair (x,x+1): s[x+2]-s[x-1]
    H=np.abs(sh(s,0,2)-sh(s,0,-1)).max(-1)[:,:-1]<=step; V=np.abs(sh(s,2,0)-sh(s,-1,0)).max(-1)[:-1]<=step
    out['across']=comps(H,V,h,w)
    # edge pixels: central difference of means
    E=np.maximum(np.abs(sh(s,0,1)-sh(s,0,-1)).max(-1),np.abs(sh(s,1,0)-sh(s,-1,0)).max(-1))
    ok=E<=step
    out['pixels']=comps(ok[:,:-1]&ok[:,1:], ok[:-1]&ok[1:],h,w)
    return out

def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--heldout", default="out/matnet/heldout", help="a dataset folder with decoded.npz (train.py makes it)")
    ap.add_argument("--step", type=float, default=0.03, help="the edit's object_edges")
    a = ap.parse_args()
    d=np.load(os.path.join(a.heldout, 'decoded.npz')); res={}
    step=a.step
    for i in range(len(d['kind'])):
        photo=d['photo'][i].astype(np.float32)/255
        s=ndimage.uniform_filter(photo,size=(3,3,1),mode='nearest')
        alb=d['albedo'][i].astype(np.float32); z=np.log(np.maximum(d['depth'][i],1e-3)); v=d['valid'][i]
        h,w=z.shape
        stepz=np.zeros((h,w),bool)
        dz=np.abs(np.diff(z,axis=1))>0.1; stepz[:,1:]|=dz; stepz[:,:-1]|=dz
        dz=np.abs(np.diff(z,axis=0))>0.1; stepz[1:]|=dz; stepz[:-1]|=dz
        key=(alb*1000).astype(np.int64); key=key[...,0]*1000003+key[...,1]*1009+key[...,2]
        u,inv,cnt=np.unique(key.ravel(),return_inverse=True,return_counts=True); inv=inv.reshape(h,w)
        R=rules(s,step); k=d['kind'][i]
        for ui in np.nonzero(cnt>0.005*h*w)[0]:
            lab,n=ndimage.label((inv==ui)&v&~stepz)
            for l in range(1,n+1):
                obj=lab==l; a=obj.mean()
                if a<0.005 or a>0.3: continue
                dt=ndimage.distance_transform_edt(obj); y,x=np.unravel_index(dt.argmax(),dt.shape)
                for name,cc in R.items():
                    m=cc==cc[y,x]
                    iou=(m&obj).sum()/(m|obj).sum()
                    res.setdefault((k,name),[]).append((iou,m.sum()>2*obj.sum(),(m&obj).sum()/obj.sum()))
    print("| kind | rule | objects | IoU, median | leaks (region > 2x the object) | recall, median |")
    print("|---|---|---|---|---|---|")
    for (k, name) in sorted(res):
        r = np.array(res[(k, name)])
        print(f"| {k} | {name} | {len(r)} | {np.median(r[:, 0]):.3f} | {100 * r[:, 1].mean():.0f} % | {np.median(r[:, 2]):.3f} |")


if __name__ == "__main__":
    main()
