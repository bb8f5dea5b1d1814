use proptest::prelude::*;

use super::*;

fn format(axes: u8, data_format: DataFormat, aux: AuxFunction) -> G05Format {
    G05Format {
        axes,
        data_format,
        aux,
        ..G05Format::new(axes)
    }
}

fn encode(f: &G05Format, travels: &[i32], aux: Option<AuxWord>) -> Vec<u8> {
    let mut out = Vec::new();
    f.encode_block(1, travels, aux, &mut out).unwrap();
    out
}

fn decode_all(f: G05Format, bytes: &[u8]) -> Vec<Result<Block, G05DecodeError>> {
    let mut d = BlockDecoder::new(f).unwrap();
    d.decode(bytes).collect()
}

#[test]
fn section_9_1_example_700_microns() {
    // §9.1 (5) example: 700 µm at IS-B.
    assert_eq!(travel_word(DataFormat::Special, 700), Some(0x0A78));
    assert_eq!(travel_word(DataFormat::General, 700), Some(0x02BC));
    assert_eq!(travel_value(DataFormat::Special, 0x0A78), 700);
    assert_eq!(travel_value(DataFormat::General, 0x02BC), 700);
    let f = G05Format::new(1);
    // High byte first (protocol notes 14); check byte 0Ah + 78h = 82h.
    assert_eq!(encode(&f, &[700], None), [0x0A, 0x78, 0x82]);
    let g = G05Format {
        data_format: DataFormat::General,
        ..f
    };
    assert_eq!(encode(&g, &[700], None), [0x02, 0xBC, 0xBE]);
}

#[test]
fn negative_travels_are_twos_complement_in_both_formats() {
    assert_eq!(travel_word(DataFormat::General, -1), Some(0xFFFF));
    assert_eq!(travel_word(DataFormat::General, -700), Some(0xFD44));
    // Special: the 14-bit two's complement spread over 15–9 and 7–1: -1 = 3FFFh.
    assert_eq!(travel_word(DataFormat::Special, -1), Some(0xFEFE));
    // -700 = 3D44h in 14 bits: 1111010 (15–9), 1000100 (7–1).
    assert_eq!(travel_word(DataFormat::Special, -700), Some(0xF488));
    for format in [DataFormat::Special, DataFormat::General] {
        for v in [-1, -2, -700, -8192, 1, 8191] {
            let w = travel_word(format, v).unwrap();
            assert_eq!(i32::from(travel_value(format, w)), v, "{format} {v}");
        }
    }
}

#[test]
fn travel_limits_of_both_formats() {
    let cases = [
        (DataFormat::Special, -8192, 8191),
        (DataFormat::General, -32768, 32767),
    ];
    for (format, min, max) in cases {
        assert_eq!(format.travel_range(), (min, max));
        for ok in [min, max] {
            let w = travel_word(format, ok).unwrap();
            assert_eq!(i32::from(travel_value(format, w)), ok);
        }
        assert_eq!(travel_word(format, min - 1), None);
        assert_eq!(travel_word(format, max + 1), None);
        let f = G05Format {
            data_format: format,
            ..G05Format::new(3)
        };
        let mut out = vec![0xEE];
        for (axis, bad) in [(1usize, min - 1), (3, max + 1)] {
            let mut travels = [0, 5, 0];
            travels[axis - 1] = bad;
            let err = f.encode_block(7, &travels, None, &mut out).unwrap_err();
            assert_eq!(
                err,
                G05EncodeError::Travel {
                    block: 7,
                    axis,
                    value: bad,
                    min,
                    max,
                    format,
                }
            );
            let text = err.to_string();
            assert!(text.contains("block 7, axis"), "{text}");
            assert!(text.contains(&bad.to_string()), "{text}");
            assert!(text.contains("§9.1"), "{text}");
        }
        assert_eq!(out, [0xEE], "a refused block leaves the output as it was");
    }
    // Special extremes on the line: 8191 = 1FFFh → 3F, FE; -8192 = 2000h → 40, 00.
    assert_eq!(travel_word(DataFormat::Special, 8191), Some(0x7EFE));
    assert_eq!(travel_word(DataFormat::Special, -8192), Some(0x8000));
    assert_eq!(travel_word(DataFormat::General, -32768), Some(0x8000));
}

#[test]
fn auxiliary_word_both_formats_both_orders() {
    // Special: 27 bits in 30–25, 23–17, 15–9, 7–1; MSB = significant.
    let aux = AuxWord::significant(3);
    assert_eq!(aux_word(DataFormat::Special, aux), Some(0x8000_0006));
    assert_eq!(aux_word(DataFormat::General, aux), Some(0x8000_0003));
    // 1000 = 0000000 0000111 1101000 → bits 15–9 = 0000111, 7–1 = 1101000.
    assert_eq!(
        aux_word(DataFormat::Special, AuxWord::significant(1000)),
        Some(0x8000_0ED0)
    );
    let max = DataFormat::Special.aux_max();
    assert_eq!(max, 134_217_727);
    assert_eq!(
        aux_word(DataFormat::Special, AuxWord::significant(max)),
        Some(0xFEFE_FEFE)
    );
    assert_eq!(
        aux_word(
            DataFormat::Special,
            AuxWord {
                value: max,
                significant: false
            }
        ),
        Some(0x7EFE_FEFE)
    );
    assert_eq!(
        aux_word(DataFormat::Special, AuxWord::significant(max + 1)),
        None
    );
    let gmax = DataFormat::General.aux_max();
    assert_eq!(
        aux_word(DataFormat::General, AuxWord::significant(gmax)),
        Some(0xFFFF_FFFF)
    );
    assert_eq!(
        aux_word(DataFormat::General, AuxWord::significant(gmax + 1)),
        None
    );
    for format in [DataFormat::Special, DataFormat::General] {
        for a in [
            AuxWord::significant(0),
            AuxWord::significant(6),
            AuxWord::significant(format.aux_max()),
            AuxWord {
                value: 12345,
                significant: false,
            },
        ] {
            assert_eq!(aux_value(format, aux_word(format, a).unwrap()), a);
        }
    }
    // The word's bytes: high half first by default, low half first as an option; each half
    // high byte first.
    assert_eq!(
        aux_bytes(AuxOrder::HighFirst, 0x8000_0ED0),
        [0x80, 0x00, 0x0E, 0xD0]
    );
    assert_eq!(
        aux_bytes(AuxOrder::LowFirst, 0x8000_0ED0),
        [0x0E, 0xD0, 0x80, 0x00]
    );
    for order in [AuxOrder::HighFirst, AuxOrder::LowFirst] {
        assert_eq!(
            aux_from_bytes(order, aux_bytes(order, 0x1234_5678)),
            0x1234_5678
        );
    }
    // In a block: axis words, then the auxiliary word, then the check byte.
    let f = G05Format {
        aux: AuxFunction::M,
        ..G05Format::new(1)
    };
    let block = encode(&f, &[700], Some(AuxWord::significant(1000)));
    let ck = [0x0A, 0x78, 0x80, 0x00, 0x0E, 0xD0]
        .iter()
        .fold(0u8, |s, &b| s.wrapping_add(b));
    assert_eq!(block, [0x0A, 0x78, 0x80, 0x00, 0x0E, 0xD0, ck]);
    let low = G05Format {
        aux_order: AuxOrder::LowFirst,
        ..f
    };
    let block = encode(&low, &[700], Some(AuxWord::significant(1000)));
    assert_eq!(block, [0x0A, 0x78, 0x0E, 0xD0, 0x80, 0x00, ck]);
    let got = decode_all(low, &block);
    let b = got[0].as_ref().unwrap();
    assert_eq!(b.aux(), Some(AuxWord::significant(1000)));
    // The same bytes read with the other order are another word.
    let got = decode_all(f, &block);
    assert_ne!(
        got[0].as_ref().unwrap().aux(),
        Some(AuxWord::significant(1000))
    );
    // General format, not significant.
    let g = G05Format {
        data_format: DataFormat::General,
        aux: AuxFunction::S,
        ..G05Format::new(2)
    };
    let a = AuxWord {
        value: 0x0102_0304,
        significant: false,
    };
    let block = encode(&g, &[-1, 1], Some(a));
    assert_eq!(
        &block[..8],
        [0xFF, 0xFF, 0x00, 0x01, 0x01, 0x02, 0x03, 0x04]
    );
    assert_eq!(decode_all(g, &block)[0].as_ref().unwrap().aux(), Some(a));
}

#[test]
fn auxiliary_errors_name_block_value_and_limit() {
    let f = G05Format {
        aux: AuxFunction::T,
        ..G05Format::new(2)
    };
    let mut out = Vec::new();
    let err = f
        .encode_block(3, &[1, 1], Some(AuxWord::significant(1 << 27)), &mut out)
        .unwrap_err();
    assert_eq!(
        err,
        G05EncodeError::AuxValue {
            block: 3,
            value: 1 << 27,
            max: (1 << 27) - 1,
            format: DataFormat::Special,
        }
    );
    assert!(err.to_string().contains("134217727"), "{err}");
    assert!(err.to_string().contains("§9.1 (8)"), "{err}");
    let plain = G05Format::new(2);
    assert_eq!(
        plain.encode_block(4, &[1, 1], Some(AuxWord::significant(3)), &mut out),
        Err(G05EncodeError::AuxOff { block: 4 })
    );
    assert_eq!(
        plain.encode_block(5, &[1], None, &mut out),
        Err(G05EncodeError::AxisCount {
            block: 5,
            given: 1,
            axes: 2
        })
    );
    assert!(out.is_empty());
}

#[test]
fn check_byte_is_the_low_byte_of_the_sum() {
    assert_eq!(check_byte(&[]), 0);
    assert_eq!(check_byte(&[0xFF, 0x02]), 0x01);
    assert_eq!(check_byte(&[0x80; 4]), 0x00);
    let f = G05Format::new(3);
    let block = encode(&f, &[8191, 8191, 8191], None);
    // 3 × (7Eh + FEh) = 3 × 17Ch = 474h → 74h.
    assert_eq!(block, [0x7E, 0xFE, 0x7E, 0xFE, 0x7E, 0xFE, 0x74]);
}

#[test]
fn end_block_is_all_zero_and_ends_binary_mode() {
    for f in [
        G05Format::new(3),
        format(2, DataFormat::General, AuxFunction::M),
    ] {
        let mut out = vec![0x55];
        f.encode_end(&mut out);
        assert_eq!(out.len(), 1 + f.block_len());
        assert!(out[1..].iter().all(|&b| b == 0));
        let got = decode_all(f, &out[1..]);
        assert_eq!(got.len(), 1);
        let b = got[0].as_ref().unwrap();
        assert!(b.is_end());
        assert!(b.travels().iter().all(|&t| t == 0));
    }
    // Zero travels with a significant auxiliary word (M00) is no end block.
    let f = format(1, DataFormat::Special, AuxFunction::M);
    let block = encode(&f, &[0], Some(AuxWord::significant(0)));
    assert!(!decode_all(f, &block)[0].as_ref().unwrap().is_end());
    // A block that would be all zero is refused: the CNC would leave binary mode.
    let mut out = Vec::new();
    assert_eq!(
        G05Format::new(2).encode_block(9, &[0, 0], None, &mut out),
        Err(G05EncodeError::ZeroBlock { block: 9 })
    );
    assert_eq!(
        f.encode_block(9, &[0], None, &mut out),
        Err(G05EncodeError::ZeroBlock { block: 9 })
    );
    assert!(out.is_empty());
    // Zero travels and a zero check byte that is wrong: SR0890, not the end.
    let got = decode_all(G05Format::new(1), &[0, 0, 1]);
    assert!(matches!(
        got[0],
        Err(G05DecodeError::CheckByte {
            block: 1,
            received: 1,
            computed: 0
        })
    ));
}

#[test]
fn block_lengths_and_parameters() {
    assert_eq!(G05Format::new(3).block_len(), 7);
    assert_eq!(
        format(3, DataFormat::Special, AuxFunction::M).block_len(),
        11
    );
    assert_eq!(
        format(MAX_AXES, DataFormat::General, AuxFunction::T).block_len(),
        MAX_BLOCK_LEN
    );
    assert_eq!(G05Format::new(1).param_7609(), 0);
    assert_eq!(
        format(1, DataFormat::General, AuxFunction::Second).param_7609(),
        0b1100
    );
    assert_eq!(AuxFunction::Second.param_2034(), Some(0));
    assert_eq!(AuxFunction::T.param_2034(), Some(3));
    assert_eq!(AuxFunction::None.param_2034(), None);
    // 7618: 100 → 1 ms, 001 → 2, 010 → 4, 000 → 8, 011 → 16.
    let table = [(0b100, 1), (0b001, 2), (0b010, 4), (0b000, 8), (0b011, 16)];
    for (bits, ms) in table {
        let t = UnitTime::from_param_7618(bits).unwrap();
        assert_eq!(t.ms(), ms);
        assert_eq!(t.param_7618(), bits);
        assert_eq!(UnitTime::from_ms(ms), Some(t));
        assert_eq!(t.duration(), Duration::from_millis(u64::from(ms)));
    }
    for bits in [0b101, 0b110, 0b111] {
        assert_eq!(UnitTime::from_param_7618(bits), None);
    }
    assert_eq!(UnitTime::default(), UnitTime::Ms8);
    assert!(UnitTime::try_from(3).is_err());
}

#[test]
fn transfer_rate_of_section_9_2() {
    // §9.2 example: 3 axes, no auxiliary function, 2 ms, 11 bits: 38500 bps.
    let f = G05Format {
        unit_time_ms: UnitTime::Ms2,
        ..G05Format::new(3)
    };
    assert_eq!(required_baud(&f, 11.0), 38_500);
    // With the auxiliary word: (6 + 5) × 11 / 2 × 1000.
    let m = G05Format {
        aux: AuxFunction::M,
        ..f
    };
    assert_eq!(required_baud(&m, 11.0), 60_500);
    // 16 ms: 7 × 11 / 16 × 1000 = 4812.5 → 4813 at least.
    let slow = G05Format {
        unit_time_ms: UnitTime::Ms16,
        ..f
    };
    assert_eq!(required_baud(&slow, 11.0), 4813);
    // The line's own framing: 10 bits (8N1), 10.5 (1.5 stop bits).
    assert_eq!(required_baud(&f, 10.0), 35_000);
    assert_eq!(required_baud(&f, 10.5), 36_750);
    assert_eq!(
        required_baud(
            &f,
            crate::engine::LineSettings::with_baud(9600).bits_per_char()
        ),
        38_500
    );
}

#[test]
fn validate_gives_every_problem() {
    assert!(G05Format::new(1).validate().is_empty());
    assert!(G05Format::new(MAX_AXES).validate().is_empty());
    assert_eq!(
        G05Format::new(0).validate(),
        vec![G05FormatError::Axes {
            axes: 0,
            max: MAX_AXES
        }]
    );
    assert_eq!(G05Format::new(MAX_AXES + 1).validate().len(), 1);
    let g = format(40, DataFormat::General, AuxFunction::None);
    let errors = g.validate_for(Protocol::A, Some(3));
    assert_eq!(errors.len(), 3, "{errors:?}");
    assert!(errors.contains(&G05FormatError::GeneralWithProtocolA {
        protocol: Protocol::A
    }));
    assert!(errors.contains(&G05FormatError::MoreThanControlled {
        axes: 40,
        controlled: 3
    }));
    let text = InvalidG05Format { errors }.to_string();
    assert!(
        text.contains("7635") && text.contains("§9.1 NOTE"),
        "{text}"
    );
    let g3 = format(3, DataFormat::General, AuxFunction::None);
    assert!(g3.validate_for(Protocol::B, Some(3)).is_empty());
    assert_eq!(g3.validate_for(Protocol::ExpansionA, None).len(), 1);
    assert!(BlockDecoder::new(G05Format::new(0)).is_err());
    assert!(G05Encoder::new(G05Format::new(0)).is_err());
}

#[test]
fn encoder_numbers_blocks() {
    let mut e = G05Encoder::new(G05Format::new(2)).unwrap();
    let mut out = Vec::new();
    e.block(&[1, 2], None, &mut out).unwrap();
    e.block(&[3, 4], None, &mut out).unwrap();
    let err = e.block(&[9000, 0], None, &mut out).unwrap_err();
    assert!(matches!(
        err,
        G05EncodeError::Travel {
            block: 3,
            axis: 1,
            ..
        }
    ));
    e.block(&[5, 6], None, &mut out).unwrap();
    assert_eq!(e.blocks(), 3);
    e.end(&mut out);
    assert_eq!(e.blocks(), 0);
    assert_eq!(out.len(), 4 * 5);
    let blocks: Vec<_> = decode_all(G05Format::new(2), &out)
        .into_iter()
        .map(Result::unwrap)
        .collect();
    assert_eq!(
        blocks.iter().map(Block::number).collect::<Vec<_>>(),
        [1, 2, 3, 4]
    );
    assert_eq!(blocks[2].travels(), [5, 6]);
    assert!(blocks[3].is_end());
}

#[test]
fn decoder_fed_byte_by_byte_and_in_any_split() {
    let f = format(3, DataFormat::Special, AuxFunction::S);
    let mut stream = Vec::new();
    let mut e = G05Encoder::new(f).unwrap();
    for i in 0..10 {
        e.block(
            &[i, -i, 100 * i],
            Some(AuxWord::significant(i as u32)),
            &mut stream,
        )
        .unwrap();
    }
    e.end(&mut stream);
    let whole = decode_all(f, &stream);
    assert_eq!(whole.len(), 11);
    let mut d = BlockDecoder::new(f).unwrap();
    let mut one = Vec::new();
    for &b in &stream {
        if let Some(r) = d.push(b) {
            one.push(r);
        }
        assert!(d.buffered() < f.block_len());
    }
    assert_eq!(one, whole);
    for cut in 1..stream.len() {
        let mut d = BlockDecoder::new(f).unwrap();
        let mut got: Vec<_> = d.decode(&stream[..cut]).collect();
        got.extend(d.decode(&stream[cut..]));
        assert_eq!(got, whole, "split at {cut}");
    }
    let b5 = whole[5].as_ref().unwrap();
    assert_eq!(b5.travels(), [5, -5, 500]);
    assert_eq!(b5.aux(), Some(AuxWord::significant(5)));
    assert_eq!(b5.number(), 6);
    assert!(whole[10].as_ref().unwrap().is_end());
}

#[test]
fn corrupted_check_byte_is_sr0890_and_the_next_block_still_decodes() {
    let f = G05Format::new(2);
    let mut stream = Vec::new();
    f.encode_block(1, &[10, 20], None, &mut stream).unwrap();
    f.encode_block(2, &[30, 40], None, &mut stream).unwrap();
    stream[4] ^= 0x02;
    let got = decode_all(f, &stream);
    let err = got[0].clone().unwrap_err();
    let computed = check_byte(&stream[..4]);
    assert_eq!(
        err,
        G05DecodeError::CheckByte {
            block: 1,
            received: stream[4],
            computed,
        }
    );
    assert!(err.to_string().contains("SR0890"), "{err}");
    assert!(err.to_string().contains("§9.1 (9)"), "{err}");
    assert_eq!(got[1].as_ref().unwrap().travels(), [30, 40]);
    // A corrupted travel byte is caught the same way.
    let mut s2 = stream.clone();
    s2[4] ^= 0x02;
    s2[6] ^= 0x04;
    assert!(decode_all(f, &s2)[1].is_err());
}

#[test]
fn special_format_bits_0_8_are_ignored_on_reading() {
    // A CNC reads only the marked bits (§9.1 (5)): 0A79h reads as 700.
    assert_eq!(travel_value(DataFormat::Special, 0x0A79), 700);
    assert_eq!(travel_value(DataFormat::Special, 0x0B78), 700);
    assert_eq!(aux_value(DataFormat::Special, 0x0101_0101).value, 0);
}

#[test]
fn g05_block_starts_binary_mode() {
    fn ends(text: &[u8]) -> Vec<usize> {
        let mut e = G05Entry::default();
        text.iter()
            .enumerate()
            .filter_map(|(i, &b)| e.feed(b).then_some(i))
            .collect()
    }
    assert_eq!(ends(b"%\nO1\nG05\n"), [8]);
    assert_eq!(ends(b"G05;"), [3]);
    assert_eq!(ends(b"N10G05\n"), [6]);
    assert_eq!(ends(b"N10 G05 \r\n"), [9]);
    assert_eq!(ends(b"G5\nG005\n"), [2, 7]);
    assert_eq!(ends(b"G05(BINARY)\n"), [11]);
    // ISO, even parity: `N` 4Eh, `1` B1h, `G` 47h, `0` 30h, `5` 35h, `;` BBh.
    assert_eq!(ends(&[0x4E, 0xB1, 0x47, 0x30, 0x35, 0xBB]), [5]);
    // Other blocks and other words are no G05 block.
    for text in [
        &b"G05 P10000\n"[..],
        b"G50\n",
        b"G01 G05\n",
        b"G05X1.\n",
        b"N\nG\n",
        b"M05\n",
        b"G\n",
        b"(G05)\n",
        b"G0%5\n",
        b"NG05\n",
    ] {
        assert_eq!(
            ends(text),
            Vec::<usize>::new(),
            "{:?}",
            String::from_utf8_lossy(text)
        );
    }
    // An unclosed comment ends with its block.
    assert_eq!(ends(b"G01 (X\nG05\n"), [10]);
}

fn any_format() -> impl Strategy<Value = G05Format> {
    (
        1..=MAX_AXES,
        any::<bool>(),
        0..5usize,
        0..5usize,
        any::<bool>(),
    )
        .prop_map(|(axes, general, aux, t, low)| G05Format {
            axes,
            data_format: if general {
                DataFormat::General
            } else {
                DataFormat::Special
            },
            aux: [
                AuxFunction::None,
                AuxFunction::Second,
                AuxFunction::M,
                AuxFunction::S,
                AuxFunction::T,
            ][aux],
            unit_time_ms: UnitTime::ALL[t],
            aux_order: if low {
                AuxOrder::LowFirst
            } else {
                AuxOrder::HighFirst
            },
        })
}

/// A format and valid blocks for it (travels in range, auxiliary value in range).
/// Travels and auxiliary word of one block.
type BlockValues = (Vec<i32>, Option<AuxWord>);

fn format_and_blocks() -> impl Strategy<Value = (G05Format, Vec<BlockValues>)> {
    any_format().prop_flat_map(|f| {
        let (min, max) = f.data_format.travel_range();
        let aux = if f.aux.rax() {
            prop::option::of(
                (0..=f.data_format.aux_max(), any::<bool>())
                    .prop_map(|(value, significant)| AuxWord { value, significant }),
            )
            .boxed()
        } else {
            Just(None).boxed()
        };
        let block = (prop::collection::vec(min..=max, usize::from(f.axes)), aux);
        (Just(f), prop::collection::vec(block, 1..20))
    })
}

proptest! {
    #[test]
    fn encode_decode_round_trip((f, blocks) in format_and_blocks()) {
        let mut e = G05Encoder::new(f).unwrap();
        let mut stream = Vec::new();
        let mut sent = Vec::new();
        for (travels, aux) in &blocks {
            match e.block(travels, *aux, &mut stream) {
                Ok(()) => sent.push((travels.clone(), *aux)),
                Err(G05EncodeError::ZeroBlock { .. }) => {
                    prop_assert!(travels.iter().all(|&t| t == 0));
                }
                Err(err) => prop_assert!(false, "{err}"),
            }
        }
        e.end(&mut stream);
        prop_assert_eq!(stream.len(), (sent.len() + 1) * f.block_len());
        let got = decode_all(f, &stream);
        prop_assert_eq!(got.len(), sent.len() + 1);
        for (block, (travels, aux)) in got.iter().zip(&sent) {
            let block = block.as_ref().unwrap();
            prop_assert!(!block.is_end());
            let back: Vec<i32> = block.travels().iter().map(|&t| i32::from(t)).collect();
            prop_assert_eq!(&back, travels);
            let expected = match (f.aux.rax(), aux) {
                (false, _) => None,
                (true, None) => Some(AuxWord::default()),
                (true, Some(a)) => Some(*a),
            };
            prop_assert_eq!(block.aux(), expected);
        }
        prop_assert!(got.last().unwrap().as_ref().unwrap().is_end());
    }

    #[test]
    fn special_format_bytes_are_all_even((f, blocks) in format_and_blocks()) {
        let f = G05Format { data_format: DataFormat::Special, ..f };
        let mut stream = Vec::new();
        for (travels, aux) in &blocks {
            // Travels and aux drawn for the general format may not fit the special one.
            let _ = f.encode_block(1, travels, *aux, &mut stream);
        }
        f.encode_end(&mut stream);
        for &b in &stream {
            prop_assert_eq!(b % 2, 0);
            prop_assert!(b != 0x0D && b != 0x03);
        }
    }

    #[test]
    fn arbitrary_bytes_never_panic(f in any_format(), bytes in prop::collection::vec(any::<u8>(), 0..600), cut in any::<usize>()) {
        let mut d = BlockDecoder::new(f).unwrap();
        let cut = cut % (bytes.len() + 1);
        let mut n = d.decode(&bytes[..cut]).count();
        n += d.decode(&bytes[cut..]).count();
        prop_assert_eq!(n, bytes.len() / f.block_len());
        prop_assert!(d.buffered() < f.block_len());
        let mut e = G05Entry::default();
        for &b in &bytes {
            let _ = e.feed(b);
        }
    }

    #[test]
    fn decoded_blocks_encode_back(f in any_format(), bytes in prop::collection::vec(any::<u8>(), 0..400)) {
        // Mostly valid check bytes: fix every block's check byte half of the time.
        let len = f.block_len();
        let mut bytes = bytes;
        for (i, chunk) in bytes.chunks_mut(len).enumerate() {
            if i % 2 == 0 && chunk.len() == len {
                let ck = check_byte(&chunk[..len - 1]);
                chunk[len - 1] = ck;
            }
        }
        let mut d = BlockDecoder::new(f).unwrap();
        let decoded: Vec<_> = d.decode(&bytes).collect();
        for (raw, result) in bytes.chunks_exact(len).zip(decoded) {
            let Ok(block) = result else {
                prop_assert_ne!(check_byte(&raw[..len - 1]), raw[len - 1]);
                continue;
            };
            prop_assert_eq!(block.is_end(), raw.iter().all(|&b| b == 0));
            if block.is_end() {
                continue;
            }
            let travels: Vec<i32> = block.travels().iter().map(|&t| i32::from(t)).collect();
            let mut again = Vec::new();
            match f.encode_block(1, &travels, block.aux(), &mut again) {
                Ok(()) => {
                    if f.data_format == DataFormat::General || raw.iter().all(|&b| b % 2 == 0) {
                        prop_assert_eq!(&again[..], raw);
                    }
                    let back = decode_all(f, &again).remove(0).unwrap();
                    prop_assert_eq!(back.travels(), block.travels());
                    prop_assert_eq!(back.aux(), block.aux());
                }
                Err(G05EncodeError::ZeroBlock { .. }) => {
                    prop_assert_eq!(f.data_format, DataFormat::Special);
                }
                Err(e) => prop_assert!(false, "{e}"),
            }
        }
    }

    #[test]
    fn travel_words_round_trip(v in -32768i32..=32767) {
        for format in [DataFormat::Special, DataFormat::General] {
            let (min, max) = format.travel_range();
            match travel_word(format, v) {
                Some(w) => {
                    prop_assert!(v >= min && v <= max);
                    prop_assert_eq!(i32::from(travel_value(format, w)), v);
                }
                None => prop_assert!(v < min || v > max),
            }
        }
    }
}
