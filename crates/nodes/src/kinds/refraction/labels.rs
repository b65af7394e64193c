//! `refraction_labels`: what the object is, seen from a viewpoint.

use super::*;

pub struct RefractionLabelsNode;

pub(crate) const LABELS_INFO: NodeInfo = NodeInfo {
    kind: "refraction_labels",
    version: 1,
    doc: "One sample's labels for the refraction-length network: the object's mask, depth, \
         normals, eq. 24 refraction length (by the object's size, in [0, 1]) and the \
         transparency edit's d1, d2, per pixel centre (`matflow dataset` makes these).",
    params: &COMMON,
    outputs: &[
        OutputSpec {
            name: "mask.png",
            ty: "file",
            doc: "8-bit: 255 where the object is seen",
        },
        OutputSpec {
            name: "depth.npy",
            ty: "file",
            doc: "f16 H×W: camera-space depth of the object (0 elsewhere)",
        },
        OutputSpec {
            name: "normal.npy",
            ty: "file",
            doc: "f16 H×W×3: outward normal in camera space (+z to the camera)",
        },
        OutputSpec {
            name: "length.npy",
            ty: "file",
            doc: "f16 H×W: eq. 24 length / object_size, clamped to [0, 1]",
        },
        OutputSpec {
            name: "d1.npy",
            ty: "file",
            doc: "f16 H×W: from entering the object to finally leaving it (scene units)",
        },
        OutputSpec {
            name: "d2.npy",
            ty: "file",
            doc: "f16 H×W: from leaving the object to the ground behind (0: nothing behind)",
        },
    ],
};

impl Node for RefractionLabelsNode {
    fn info(&self) -> &'static NodeInfo {
        &LABELS_INFO
    }
    fn check(&self, p: &Params) -> Result<(), String> {
        check_object(p)
    }
    fn film_size(&self, p: &Params) -> Option<(usize, usize)> {
        let n = p.i64("size") as usize;
        Some((n, n))
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let v = view(p)?;
        let l = object_labels(
            &v.camera,
            &v.object,
            v.hollow,
            v.ground.as_ref().map(|g| &g.0),
        );
        let (w, h) = (v.camera.width, v.camera.height);
        let size = p.f32("object_size");
        let finite = |x: f32| if x.is_finite() { x } else { 0.0 };
        let gray = |img: &matflow_scene::GrayImage, f: &dyn Fn(f32) -> f32| {
            let vals: Vec<f32> = img.data.iter().map(|&x| f(finite(x))).collect();
            npy::encode(&vals, &[h, w], Dtype::F16)
        };
        let normals: Vec<f32> = l
            .normal
            .data
            .iter()
            .flat_map(|n| [finite(n.x), finite(n.y), finite(n.z)])
            .collect();
        let mut out = BTreeMap::new();
        out.insert(
            "mask.png".into(),
            io::png_mask_bytes(&l.mask).map_err(failed)?,
        );
        out.insert("depth.npy".into(), gray(&l.depth, &|x| x));
        out.insert(
            "normal.npy".into(),
            npy::encode(&normals, &[h, w, 3], Dtype::F16),
        );
        out.insert(
            "length.npy".into(),
            gray(&l.length, &|x| (x / size).clamp(0.0, 1.0)),
        );
        out.insert("d1.npy".into(), gray(&l.d1, &|x| x.max(0.0)));
        out.insert("d2.npy".into(), gray(&l.d2, &|x| x.max(0.0)));
        Ok(out)
    }
}
