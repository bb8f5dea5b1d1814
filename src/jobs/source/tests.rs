use super::*;
use cellgate_core::fanuc::{EndCode, Protocol};

fn rules(protocol: Protocol) -> ProgramRules {
    ProgramRules {
        protocol,
        end_code: EndCode::Cr,
        max_size: 1 << 20,
    }
}

#[tokio::test]
async fn program_files_are_scanned_and_streamed_whole_or_from_a_block() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("p");
    let program: Vec<u8> = b"%\nO1\n"
        .iter()
        .copied()
        .chain(std::iter::repeat_n(b"G01X1\n".iter().copied(), 30_000).flatten())
        .collect();
    std::fs::write(&path, &program).unwrap();
    let report = scan_file(rules(Protocol::A), &path).await.unwrap();
    assert_eq!(report.size, program.len() as u64);
    assert!(!report.has_eor);
    assert_eq!(report.o_number.as_deref(), Some("O1"));

    let read = |start| {
        let path = path.clone();
        async move {
            let mut out = Vec::new();
            open_stream(&path, b"%", start)
                .await
                .unwrap()
                .read_to_end(&mut out)
                .await
                .unwrap();
            out
        }
    };
    let mut whole = program.clone();
    whole.push(b'%');
    assert_eq!(read(None).await, whole);
    // The header (first two lines), then from the last block on: the suffix follows.
    let body_start = program.len() as u64 - 6;
    let out = read(Some(StartPoint {
        header_end: 5,
        body_start,
    }))
    .await;
    assert_eq!(out, b"%\nO1\nG01X1\n%");
    // A start inside the appended suffix itself.
    let out = read(Some(StartPoint {
        header_end: 2,
        body_start: program.len() as u64,
    }))
    .await;
    assert_eq!(out, b"%\n%");

    std::fs::write(&path, b"%\nO1\n\x0d\n%").unwrap();
    assert!(matches!(
        scan_file(rules(Protocol::A), &path).await,
        Err(ScanFileError::Program(ProgramError::EndCodeInData {
            offset: 5,
            ..
        }))
    ));
    assert!(matches!(
        scan_file(rules(Protocol::A), &dir.path().join("nope")).await,
        Err(ScanFileError::Io(_))
    ));
}
