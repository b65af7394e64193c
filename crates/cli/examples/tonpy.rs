// Debug helper (not committed): convert EXR/HDR to raw f32 .npy for numpy.
use std::path::Path;
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let p = Path::new(&args[1]);
    let out = &args[2];
    let img = if p.extension().unwrap() == "hdr" {
        matflow_scene::io::read_hdr(p).unwrap()
    } else {
        match matflow_scene::io::read_exr_rgb(p) {
            Ok(i) => i,
            Err(_) => {
                let g = matflow_scene::io::read_exr_gray(p).unwrap();
                matflow_scene::Image::from_vec(
                    g.width,
                    g.height,
                    g.data.iter().map(|v| glam::Vec3::splat(*v)).collect(),
                )
            }
        }
    };
    let hdr = format!(
        "{{'descr': '<f4', 'fortran_order': False, 'shape': ({}, {}, 3), }}",
        img.height, img.width
    );
    let mut h = hdr.into_bytes();
    while (h.len() + 11) % 64 != 0 {
        h.push(b' ');
    }
    h.push(b'\n');
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend_from_slice(&(h.len() as u16).to_le_bytes());
    b.extend_from_slice(&h);
    for v in &img.data {
        for c in [v.x, v.y, v.z] {
            b.extend_from_slice(&c.to_le_bytes());
        }
    }
    std::fs::write(out, b).unwrap();
}
