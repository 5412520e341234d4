//! Named fields (Blueprint-shaped steps) through real daemons: the generator-node renders the
//! field its scene names (`GenerationConfig.field`, changed live) and skips the rest, so the
//! VDI it stores equals that field pushed alone; cell data lands at its cells' centres; a
//! field the scene names but the step lacks, and a field whose values do not fill the brick,
//! are refused by name.

use crate::common::{field, generator, small_config, viz};
use insitu_client::{Field, GenerationConfig, SimClient, Step};
use insitu_core::vdi::{codec, Vdi};
use insitu_e2e::rt;
use std::path::Path;

fn vdi(rec: &Path, step: u64) -> Vdi {
    let bytes = std::fs::read(rec.join(format!("step_{step:08}_rank_0000.vdi"))).unwrap();
    codec::decode(&bytes, &Default::default()).unwrap()
}

#[test]
fn the_field_the_scene_names_is_rendered_and_the_others_skipped() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let g = generator(&small_config(&v.addr, "block", 4), tmp.path(), &[]);
    let b = field(16, 5);
    let cells: Vec<f32> = (0..15 * 15 * 15)
        .map(|i| ((i % 15) as f32 / 14.0).powi(2))
        .collect();
    let named = |step: u64| {
        Step::whole_f32(step, 0.0, [16; 3], &[]).with_fields(vec![
            Field::vertex_f32("a", &field(16, 1)),
            Field::vertex_f32("b", &b),
            Field::element_f32("c", &cells),
        ])
    };
    let scene = |name: &str| GenerationConfig {
        resolution: 32,
        gamma: 0.01,
        field: Some(name.into()),
        ..Default::default()
    };
    rt().block_on(async {
        let mut sim = SimClient::connect(&g.addr, None).await.unwrap();
        // b alone, as every client before named fields pushes it; then among others.
        sim.push_step(Step::whole_f32(1, 0.0, [16; 3], &b))
            .await
            .unwrap();
        sim.set_config(scene("b")).await.unwrap();
        sim.push_step(named(2)).await.unwrap();
        sim.set_config(scene("c")).await.unwrap();
        sim.push_step(named(3)).await.unwrap();
        sim.set_config(scene("pressure")).await.unwrap();
        let e = sim.push_step(named(4)).await.unwrap_err().to_string();
        assert!(
            e.contains("step 4 has no field \"pressure\"; fields here: a, b, c"),
            "{e}"
        );
        // "" names each step's first.
        sim.set_config(scene("")).await.unwrap();
        let mut short = named(5);
        short.fields[2].values = short.fields[2].values.slice(4..);
        let e = sim.push_step(short).await.unwrap_err().to_string();
        assert!(
            e.contains("field \"c\": 13496 bytes for the 3375 cells"),
            "{e}"
        );
        sim.push_step(named(5)).await.unwrap();
        let s = sim.flush(std::time::Duration::from_secs(60)).await.unwrap();
        assert_eq!((s.steps_received, s.steps_shipped), (4, 4));
    });
    assert_eq!(vdi(&rec, 2), vdi(&rec, 1), "b among fields is b alone");
    let c = vdi(&rec, 3).meta().volume_box;
    assert_eq!(
        (c.min.to_array(), c.max.to_array()),
        ([0.5; 3], [14.5; 3]),
        "cell data at its cells' centres"
    );
    assert_ne!(vdi(&rec, 5), vdi(&rec, 2), "the first field, a, is not b");
    assert_eq!(vdi(&rec, 5).meta().volume_box.max.to_array(), [15.0; 3]);
    g.terminate();
    v.terminate();
}
