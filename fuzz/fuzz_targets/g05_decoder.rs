//! Feeds the G05 block decoder (§9.1) arbitrary bytes in arbitrary pieces, under a format
//! taken from the first bytes (axes, special or general format, auxiliary word and its
//! order, unit time), and the `G05` block finder the same bytes. It must never panic, never
//! hold a whole block, and count blocks exactly: one per block length of bytes. A block it
//! accepts encodes back to the same bytes (in the special format, when no ignored bit 0, 8,
//! 16 or 24 was set), and decodes again to the same block.
#![no_main]

use cellgate_core::fanuc::g05::{
    AuxFunction, AuxOrder, BlockDecoder, DataFormat, G05EncodeError, G05Entry, G05Format, MAX_AXES,
    UnitTime,
};
use libfuzzer_sys::fuzz_target;

fn pick<T: Copy>(options: &[T], b: u8) -> T {
    options[usize::from(b) % options.len()]
}

fuzz_target!(|data: &[u8]| {
    let Some((head, mut rest)) = data.split_at_checked(3) else {
        return;
    };
    let format = G05Format {
        // 0 and more than MAX_AXES too: the decoder must refuse them, not panic.
        axes: head[0] % (MAX_AXES + 2),
        data_format: pick(&[DataFormat::Special, DataFormat::General], head[1]),
        aux: pick(
            &[
                AuxFunction::None,
                AuxFunction::Second,
                AuxFunction::M,
                AuxFunction::S,
                AuxFunction::T,
            ],
            head[1] >> 1,
        ),
        unit_time_ms: pick(&UnitTime::ALL, head[2]),
        aux_order: pick(&[AuxOrder::HighFirst, AuxOrder::LowFirst], head[2] >> 4),
    };
    let Ok(mut decoder) = BlockDecoder::new(format) else {
        assert!(!format.validate().is_empty());
        return;
    };
    let len = format.block_len();
    let mut entry = G05Entry::default();
    // Every byte fed, to compare blocks with what they were decoded from.
    let mut fed: Vec<u8> = Vec::with_capacity(rest.len());
    let mut blocks = 0usize;
    let mut again = Vec::with_capacity(len);
    while let Some((&cut, tail)) = rest.split_first() {
        let (piece, next) = tail.split_at(usize::from(cut).min(tail.len()));
        rest = next;
        for &b in piece {
            let _ = entry.feed(b);
        }
        fed.extend_from_slice(piece);
        for result in decoder.decode(piece) {
            blocks += 1;
            let raw = &fed[(blocks - 1) * len..blocks * len];
            let Ok(block) = result else {
                continue;
            };
            assert_eq!(block.number(), blocks as u64);
            assert_eq!(block.travels().len(), usize::from(format.axes));
            assert_eq!(block.aux().is_some(), format.aux.rax());
            assert_eq!(block.is_end(), raw.iter().all(|&b| b == 0));
            if block.is_end() {
                continue;
            }
            let travels: Vec<i32> = block.travels().iter().map(|&t| i32::from(t)).collect();
            again.clear();
            match format.encode_block(1, &travels, block.aux(), &mut again) {
                Ok(()) => {
                    let exact = format.data_format == DataFormat::General
                        || raw.iter().all(|&b| b % 2 == 0);
                    if exact {
                        assert_eq!(&again[..], raw);
                    }
                    let mut d = BlockDecoder::new(format).unwrap();
                    let back = d.decode(&again).next().unwrap().unwrap();
                    assert_eq!(back.travels(), block.travels());
                    assert_eq!(back.aux(), block.aux());
                }
                // Only ignored bits made the bytes non-zero.
                Err(G05EncodeError::ZeroBlock { .. }) => {
                    assert_eq!(format.data_format, DataFormat::Special);
                }
                Err(e) => panic!("a decoded block does not encode: {e}"),
            }
        }
        assert!(decoder.buffered() < len);
        assert_eq!(decoder.blocks(), (fed.len() / len) as u64);
    }
});
