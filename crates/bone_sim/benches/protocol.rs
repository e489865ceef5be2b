//! Criterion bench of the force message's encoding, which every pose's thread runs once a tick:
//! a force at the device's peak, every field written, the force and guidance components rounded
//! toward zero so that float32 never puts them over the peak (`encode_force`).

use std::hint::black_box;

use bone_sim::protocol::{encode_force, ForceMsg};
use criterion::{criterion_group, criterion_main, Criterion};
use nalgebra::Vector3;

fn encode(c: &mut Criterion) {
    // 256 forces at the Touch's 3.3 N peak in directions spread over the sphere.
    let forces: Vec<Vector3<f64>> = (0..256)
        .map(|i| {
            let (a, b) = (f64::from(i) * 0.37, f64::from(i) * 0.91);
            Vector3::new(a.sin() * b.cos(), a.sin() * b.sin(), a.cos()) * 3.3
        })
        .collect();
    let mut k = 0usize;
    c.bench_function("encode_force", |b| {
        b.iter(|| {
            k = (k + 1) & 255;
            let f = forces[k];
            black_box(encode_force(black_box(&ForceMsg { force_n: f, guidance_n: f * 0.2, ..Default::default() })))
        });
    });
}

criterion_group!(benches, encode);
criterion_main!(benches);
