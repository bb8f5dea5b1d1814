//! Feeds the FFU120B text decoder arbitrary bytes in arbitrary pieces, under settings taken
//! from the first bytes (start and end codes, their Set 1 / Set 2 bytes, transposition, BCC
//! kind, range, calculation and code, command-set or non-procedure length). It must never
//! panic, never hold more than the module's 512-byte buffer, and every text it returns must
//! fit the bounds it was given.
#![no_main]

use cellgate_core::fuji::frame::{
    BccCalc, BccCode, BccKind, BccRange, Crc16, EndCode, FrameDecoder, FrameSettings,
    MAX_COMMAND_TEXT, MAX_NON_PROCEDURE_TEXT, RX_BUFFER, StartCode,
    TransmissionCode,
};
use libfuzzer_sys::fuzz_target;

fn pick<T: Copy>(options: &[T], b: u8) -> T {
    options[usize::from(b) % options.len()]
}

fuzz_target!(|data: &[u8]| {
    let Some((head, mut rest)) = data.split_at_checked(8) else {
        return;
    };
    let settings = FrameSettings {
        start_code: pick(
            &[
                StartCode::None,
                StartCode::Stx,
                StartCode::Colon,
                StartCode::DoubleColon,
                StartCode::Set1,
                StartCode::Set2,
            ],
            head[0],
        ),
        // Set bytes of any count, right or wrong: the decoder must cope with both.
        start_codes: head[6..8]
            .iter()
            .take(usize::from(head[0] >> 6))
            .copied()
            .collect(),
        end_code: pick(
            &[
                EndCode::Etx,
                EndCode::Cr,
                EndCode::Lf,
                EndCode::CrLf,
                EndCode::DleEtx,
                EndCode::Set1,
                EndCode::Set2,
            ],
            head[1],
        ),
        end_codes: head[5..7]
            .iter()
            .take(usize::from(head[1] >> 6))
            .copied()
            .collect(),
        transposition: head[2] & 1 == 0,
        code: pick(
            &[TransmissionCode::Ascii, TransmissionCode::Ebcdic],
            head[2] >> 3,
        ),
        bcc: pick(&[BccKind::None, BccKind::Set1, BccKind::Set2], head[2] >> 1),
        bcc_range: pick(
            &[
                BccRange::Text,
                BccRange::TextEnd,
                BccRange::StartText,
                BccRange::StartTextEnd,
            ],
            head[3],
        ),
        bcc_calc: pick(
            &[
                BccCalc::Add,
                BccCalc::AddInvert,
                BccCalc::Eor,
                BccCalc::Crc16,
            ],
            head[3] >> 2,
        ),
        bcc_code: pick(&[BccCode::TransmissionCode, BccCode::Binary], head[3] >> 4),
        crc16: pick(&[Crc16::Arc, Crc16::Buypass, Crc16::Modbus], head[4]),
    };
    let (mut decoder, max) = match head[4] >> 4 {
        0..=9 => (FrameDecoder::command_set(&settings), MAX_COMMAND_TEXT),
        10..=12 => (
            FrameDecoder::non_procedure(&settings, None),
            MAX_NON_PROCEDURE_TEXT,
        ),
        _ => (
            FrameDecoder::non_procedure(&settings, Some(usize::from(head[5]) + 1)),
            RX_BUFFER,
        ),
    };
    while let Some((&cut, tail)) = rest.split_first() {
        let (piece, next) = tail.split_at(usize::from(cut).min(tail.len()));
        rest = next;
        for text in decoder.decode(piece).into_iter().flatten() {
            assert!(text.len() <= max);
        }
        assert!(decoder.buffered() <= RX_BUFFER);
        if cut == 0xFF {
            decoder.clear();
            assert_eq!(decoder.buffered(), 0);
        }
    }
    let _ = decoder.counts().total();
});
