//! Round trips JSON ↔ MessagePack ↔ binary are bit-exact, for generated models (proptest); and
//! whatever the writer writes, the reader reads (spec §7.7), with nested extras up to and beyond the
//! depth limit and non-finite numbers among the generated models.

use ism_format::io::{self, ReadOptions, WriteOptions};
use ism_format::{
    Direction, Encoding, FaceRecord, JsonValue, Metadata, Model, Rule, Stage, StageKind, VertexMap,
};
use proptest::prelude::*;

/// Any finite f64, by bit pattern: subnormals, ±0, extremes included (JSON cannot carry NaN/Inf).
fn finite() -> impl Strategy<Value = f64> {
    any::<u64>()
        .prop_map(f64::from_bits)
        .prop_filter("finite", |x| x.is_finite())
}

fn json_value() -> impl Strategy<Value = JsonValue> {
    let leaf = prop_oneof![
        Just(serde_json::Value::Null),
        any::<bool>().prop_map(serde_json::Value::Bool),
        any::<i64>().prop_map(|i| serde_json::json!(i)),
        finite().prop_map(|x| serde_json::json!(x)),
        "[a-z\\u{e9}\\u{1F600}]{0,8}".prop_map(serde_json::Value::String),
    ];
    leaf.prop_recursive(3, 16, 4, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..4).prop_map(serde_json::Value::Array),
            prop::collection::btree_map("[a-z]{1,5}", inner, 0..4)
                .prop_map(|m| serde_json::Value::Object(m.into_iter().collect())),
        ]
    })
    .prop_map(JsonValue)
}

/// JSON data wrapped in `levels` arrays and objects, alternating: reaches and crosses the nesting
/// limit of spec §7.8 (the model's extras may nest `MAX_DEPTH - 1` levels).
fn nested_json_value() -> impl Strategy<Value = JsonValue> {
    (0..=ism_format::MAX_DEPTH + 2, json_value(), "[a-z]{1,3}").prop_map(|(levels, inner, key)| {
        let mut v = inner.0;
        for level in 0..levels {
            v = if level % 2 == 0 {
                serde_json::Value::Array(vec![v])
            } else {
                serde_json::json!({ key.clone(): v })
            };
        }
        JsonValue(v)
    })
}

fn stage() -> impl Strategy<Value = Stage> {
    (
        prop_oneof![
            Just(StageKind::Bezier),
            Just(StageKind::Rational),
            Just(StageKind::Monotonic)
        ],
        1u32..8,
        any::<bool>(),
        prop::option::of("[a-z ]{0,10}"),
        prop::collection::vec(
            (
                prop::collection::vec(any::<u32>(), 1..4),
                prop::collection::vec(finite(), 0..9),
                prop::collection::vec(finite(), 0..3),
            )
                .prop_map(|(face, points, weights)| FaceRecord {
                    face,
                    points,
                    weights,
                }),
            0..4,
        ),
        prop::collection::vec(
            (any::<u32>(), prop::collection::vec(finite(), 0..5)).prop_map(
                |(vertex, coefficients)| VertexMap {
                    vertex,
                    coefficients,
                },
            ),
            0..3,
        ),
        json_value(),
    )
        .prop_map(
            |(kind, degree, parametric, name, faces, vertex_maps, extras)| Stage {
                kind,
                degree,
                direction: if parametric {
                    Direction::Parametric
                } else {
                    Direction::Implicit
                },
                name,
                faces: faces.into(),
                vertex_maps,
                extras,
            },
        )
}

fn model() -> impl Strategy<Value = Model> {
    (
        2u8..=3,
        prop::collection::vec(finite(), 0..30),
        prop::collection::vec(any::<u32>(), 0..20),
        prop::collection::vec(finite(), 0..10),
        finite(),
        prop::collection::vec(stage(), 0..3),
        prop::option::of("[ -~]{0,12}"),
        prop::collection::btree_map("[A-Z]{2}_[a-z]{1,6}", json_value(), 0..2),
        prop_oneof![json_value(), nested_json_value()],
    )
        .prop_map(
            |(dimension, vertices, simplices, values, level, stages, name, extensions, extras)| {
                let mut m = Model::new(dimension);
                m.vertices = vertices;
                m.simplices = simplices;
                m.values = values;
                m.level = level;
                m.stages = stages;
                m.metadata = Metadata {
                    name,
                    generator: Some("proptest".into()),
                    units: None,
                    description: None,
                };
                m.extensions_used = extensions.keys().cloned().collect();
                m.extensions = extensions;
                m.extras = extras;
                m
            },
        )
}

/// The binary encoding writes every f64 as its 8 bytes, so equal binary payloads mean bit-equal models.
fn bits(model: &Model) -> Vec<u8> {
    io::encode_payload(model, Encoding::Binary, false).unwrap()
}

fn unchecked() -> ReadOptions {
    ReadOptions {
        check_structure: false,
        ..ReadOptions::default()
    }
}

/// Models a writer may have to refuse: any model, with at most one number made non-finite.
fn any_model() -> impl Strategy<Value = Model> {
    (
        model(),
        0usize..6,
        prop_oneof![Just(f64::NAN), Just(f64::INFINITY), Just(f64::NEG_INFINITY)],
    )
        .prop_map(|(mut m, which, bad)| {
            match which {
                0 if !m.vertices.is_empty() => m.vertices[0] = bad,
                1 if !m.values.is_empty() => m.values[0] = bad,
                2 => m.level = bad,
                3 => {
                    // The first coordinate of the first record that has points.
                    if let Some(x) = m
                        .stages
                        .iter_mut()
                        .find_map(|s| s.faces.all_points_mut().first_mut())
                    {
                        *x = bad;
                    }
                }
                _ => {}
            }
            m
        })
}

/// Whether a model's numbers are all finite and its json data within the depth limit.
fn writable(m: &Model) -> bool {
    io::check_writable(m).is_ok()
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 400, ..ProptestConfig::default() })]

    /// A file the writer writes is a file the reader reads, in every encoding; what it refuses, a
    /// reader refuses too. Re-encoding what was read gives the same bytes in every encoding
    /// (spec §7.7: one canonical form per encoding).
    #[test]
    fn whatever_the_writer_writes_the_reader_reads(m in any_model()) {
        for enc in Encoding::ALL {
            match io::to_vec(&m, enc, WriteOptions::default()) {
                Ok(bytes) => {
                    prop_assert!(writable(&m));
                    let doc = io::from_slice_with(&bytes, &unchecked());
                    prop_assert!(doc.is_ok(), "{enc:?}: wrote a file it refuses: {:?}", doc.err());
                    let read = doc.unwrap().model;
                    prop_assert_eq!(bits(&read), bits(&m));
                    for other in Encoding::ALL {
                        prop_assert_eq!(
                            io::to_vec(&read, other, WriteOptions::default()).unwrap(),
                            io::to_vec(&m, other, WriteOptions::default()).unwrap(),
                            "{:?} -> {:?}", enc, other
                        );
                    }
                }
                Err(e) => {
                    prop_assert!(!writable(&m));
                    let rule = e.rule().unwrap();
                    prop_assert!(
                        matches!(rule, Rule::Malformed | Rule::VertexArray | Rule::ValueArray | Rule::Level | Rule::NonFinite),
                        "{e}"
                    );
                    // The same model written without the checks is refused by the reader.
                    if rule == Rule::Malformed {
                        let raw = io::to_vec_unchecked(&m, enc, WriteOptions::default()).unwrap();
                        let refused = io::from_slice_with(&raw, &unchecked()).err().and_then(|e| e.rule());
                        prop_assert_eq!(refused, Some(Rule::Malformed), "{:?}: {}", enc, e);
                    } else if enc != Encoding::Json {
                        // (JSON cannot hold the number at all.) The structural checks may stop
                        // at an earlier rule (spec §9), but the file is refused.
                        let raw = io::to_vec_unchecked(&m, enc, WriteOptions::default()).unwrap();
                        prop_assert!(io::from_slice(&raw).is_err(), "{:?}: {}", enc, e);
                    }
                }
            }
        }
    }

    #[test]
    fn every_encoding_round_trips_bit_exactly(m in model().prop_filter("writable", writable)) {
        let reference = bits(&m);
        for enc in Encoding::ALL {
            for json_in_container in [false, true] {
                let bytes = io::to_vec(&m, enc, WriteOptions { pretty: json_in_container, json_in_container }).unwrap();
                let doc = io::from_slice_with(&bytes, &unchecked()).unwrap();
                prop_assert_eq!(doc.encoding, enc);
                prop_assert_eq!(bits(&doc.model), reference.clone());
            }
        }
    }

    #[test]
    fn chained_conversions_are_bit_exact(m in model().prop_filter("writable", writable)) {
        let mut current = m.clone();
        for enc in [Encoding::Json, Encoding::MessagePack, Encoding::Binary, Encoding::Json, Encoding::Binary] {
            let bytes = io::to_vec(&current, enc, WriteOptions::default()).unwrap();
            current = io::from_slice_with(&bytes, &unchecked()).unwrap().model;
        }
        prop_assert_eq!(bits(&current), bits(&m));
    }
}

#[test]
fn special_values_survive_json() {
    let mut m = Model::new(2);
    m.vertices = vec![
        -0.0,
        5e-324,
        f64::MAX,
        f64::MIN_POSITIVE,
        0.1 + 0.2,
        -1.0 / 3.0,
    ];
    m.values = vec![f64::EPSILON, -2.5e-308, 1e308];
    let bytes = io::to_vec(&m, Encoding::Json, WriteOptions::default()).unwrap();
    let back = io::from_slice_with(&bytes, &unchecked()).unwrap().model;
    assert_eq!(bits(&back), bits(&m));
    assert!(back.vertices[0].is_sign_negative());
}
