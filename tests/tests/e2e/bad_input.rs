//! Bad input over the wire: each is rejected with a clear status, the daemon keeps serving,
//! and nothing is half-stored or counted.

use crate::common::{field, generator, index, small_config, viz};
use bytes::Bytes;
use insitu_client::{SimClient, Step};
use insitu_e2e::rt;
use insitu_proto::auth::{AttachToken, Token};
use insitu_proto::pb::generator_client::GeneratorClient;
use insitu_proto::pb::viz_client::VizClient;
use insitu_proto::{chunk, pb, transport};
use tonic::Code;

fn header(total_bytes: u64, dtype: i32) -> pb::StepHeader {
    let d = Some(pb::Dims3 {
        x: 16,
        y: 16,
        z: 16,
    });
    pb::StepHeader {
        step: 1,
        dtype,
        global_dims: d,
        brick_offset: Some(pb::Dims3::default()),
        brick_dims: d,
        world_size: 1,
        total_bytes,
        ..Default::default()
    }
}

#[test]
fn the_generator_rejects_bad_steps_and_keeps_serving() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let cfg = small_config(&v.addr, "block", 4).replace(
        "max_backoff_secs",
        "max_step_bytes = 100000\nmax_backoff_secs",
    );
    let g = generator(&cfg, tmp.path(), &[("INSITU_TOKEN", "s3cret")]);
    let token = Token::new("s3cret", "test").unwrap();
    rt().block_on(async {
        let channel = transport::connect(&transport::uri(&g.addr)).await.unwrap();
        let mut client =
            GeneratorClient::with_interceptor(channel.clone(), AttachToken::new(Some(&token)));
        let good = Bytes::from(vec![0u8; 16 * 16 * 16 * 4]);
        let expect = |msgs: Vec<pb::StepChunk>, code: Code, words: &str| {
            let mut client = client.clone();
            let words = words.to_owned();
            async move {
                let e = client
                    .push_step(tokio_stream::iter(msgs))
                    .await
                    .unwrap_err();
                assert_eq!(e.code(), code, "{}", e.message());
                assert!(
                    e.message().contains(&words),
                    "{:?} lacks {words:?}",
                    e.message()
                );
            }
        };
        // Dims that do not match the bytes.
        expect(
            chunk::split(header(1000, pb::ScalarType::F32 as i32), good.slice(..1000)),
            Code::InvalidArgument,
            "total_bytes",
        )
        .await;
        // Unknown dtype.
        expect(
            chunk::split(header(good.len() as u64, 42), good.clone()),
            Code::InvalidArgument,
            "dtype",
        )
        .await;
        // A stream that ends early.
        let mut msgs = chunk::split::<pb::StepChunk>(
            header(good.len() as u64, pb::ScalarType::F32 as i32),
            good.clone(),
        );
        if let Some(pb::step_chunk::Part::Data(d)) = msgs.pop().and_then(|m| m.part) {
            msgs.push(pb::StepChunk {
                part: Some(pb::step_chunk::Part::Data(d.slice(..d.len() / 2))),
            });
        }
        expect(msgs, Code::InvalidArgument, "ended after").await;
        // A world of four billion ranks (the probe's): refused at the header, naming the
        // limit, instead of acknowledged and waited for.
        let world = pb::StepHeader {
            world_size: u32::MAX,
            ..header(good.len() as u64, pb::ScalarType::F32 as i32)
        };
        expect(
            chunk::split(world, good.clone()),
            Code::InvalidArgument,
            "over the limit of 1048576 ranks",
        )
        .await;
        // Two ranks each claiming the whole grid.
        let twice = pb::StepHeader {
            world_size: 2,
            ..header(good.len() as u64, pb::ScalarType::F32 as i32)
        };
        expect(
            chunk::split(twice, good.clone()),
            Code::InvalidArgument,
            "bricks do not overlap",
        )
        .await;
        // A step over the node's limit (checked before reading the payload).
        let big = header(200 * 200 * 200 * 4, pb::ScalarType::F32 as i32);
        let big = pb::StepHeader {
            global_dims: Some(pb::Dims3 {
                x: 200,
                y: 200,
                z: 200,
            }),
            brick_dims: Some(pb::Dims3 {
                x: 200,
                y: 200,
                z: 200,
            }),
            ..big
        };
        expect(
            vec![pb::StepChunk {
                part: Some(pb::step_chunk::Part::Header(big)),
            }],
            Code::ResourceExhausted,
            "limit",
        )
        .await;
        // One message over the message size limit.
        let huge = vec![
            pb::StepChunk {
                part: Some(pb::step_chunk::Part::Header(header(
                    good.len() as u64,
                    pb::ScalarType::F32 as i32,
                ))),
            },
            pb::StepChunk {
                part: Some(pb::step_chunk::Part::Data(Bytes::from(vec![0u8; 5 << 20]))),
            },
        ];
        let e = client
            .push_step(tokio_stream::iter(huge))
            .await
            .unwrap_err();
        assert!(
            matches!(
                e.code(),
                Code::OutOfRange | Code::ResourceExhausted | Code::Internal
            ),
            "{e:?}"
        );
        // Wrong and missing tokens.
        for t in [Some(Token::new("wrong", "t").unwrap()), None] {
            let mut c =
                GeneratorClient::with_interceptor(channel.clone(), AttachToken::new(t.as_ref()));
            let e = c.get_status(pb::StatusRequest {}).await.unwrap_err();
            assert_eq!(e.code(), Code::Unauthenticated);
        }
        // Still serving; none of the above was counted.
        let mut sim = SimClient::connect(&g.addr, Some(&token)).await.unwrap();
        sim.push_step(Step::whole_f32(7, 0.0, [16; 3], &field(16, 7)))
            .await
            .unwrap();
        let s = sim.flush(std::time::Duration::from_secs(60)).await.unwrap();
        assert_eq!((s.steps_received, s.steps_shipped), (1, 1));
        let _ = &mut client;
    });
    let steps: Vec<u64> = index(&rec).iter().map(|e| e.step).collect();
    assert_eq!(steps, vec![7]);
    g.terminate();
    v.terminate();
}

#[test]
fn the_viz_node_rejects_a_corrupt_vdi_and_stores_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    rt().block_on(async {
        let channel = transport::connect(&transport::uri(&v.addr)).await.unwrap();
        let mut c = VizClient::new(channel);
        let h = pb::VdiHeader {
            step: 3,
            resolution: 8,
            gamma: 0.1,
            codec: pb::Codec::Zstd as i32,
            total_bytes: 64,
            ..Default::default()
        };
        let e = c
            .ship_vdi(tokio_stream::iter(chunk::split(
                h,
                Bytes::from(vec![7u8; 64]),
            )))
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument);
        assert!(e.message().contains("step 3"), "{}", e.message());
        // A good file whose header carries a time that is not a number, or a negative one:
        // refused, naming the field (the index could not have held it).
        let (file, _) = crate::faults::vdi_and_refs(0.01);
        let good = crate::faults::header(4, &file, 0.01);
        for (field, h) in [
            (
                "tau_secs",
                pb::VdiHeader {
                    tau_secs: f64::NAN,
                    ..good.clone()
                },
            ),
            (
                "tau_compress_secs",
                pb::VdiHeader {
                    tau_compress_secs: -1.0,
                    ..good.clone()
                },
            ),
            (
                "sim_time",
                pb::VdiHeader {
                    sim_time: f64::INFINITY,
                    ..good.clone()
                },
            ),
        ] {
            let e = c
                .ship_vdi(tokio_stream::iter(chunk::split(
                    h,
                    Bytes::from(file.clone()),
                )))
                .await
                .unwrap_err();
            assert_eq!(e.code(), Code::InvalidArgument, "{field}: {e:?}");
            assert!(
                e.message().contains(field) && e.message().contains("step 4"),
                "{}",
                e.message()
            );
        }
        let s = c
            .get_status(pb::StatusRequest {})
            .await
            .unwrap()
            .into_inner();
        assert_eq!((s.vdis_stored, s.rejected), (0, 4));
    });
    assert!(index(&rec).is_empty());
    // Nothing but the (empty) index.
    let files: Vec<String> = std::fs::read_dir(&rec)
        .unwrap()
        .map(|d| d.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| !n.starts_with("index.sqlite"))
        .collect();
    assert!(files.is_empty(), "{files:?}");
    v.terminate();
}
