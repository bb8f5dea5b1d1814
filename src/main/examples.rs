//! The `Examples:` that the main commands' help ends with: commands of the default cell as
//! they are typed (tests/cli/help.rs runs each of them with `--help`).

pub const SUBMIT: &str = "\
Examples:
  cellgate submit mill-1 O1234.nc                        # send a file, follow the job to its end
  cellgate submit mill-1 --library O1234 --revision 3    # revision 3 of the library's O1234
  cellgate submit mill-1 O1234.nc --detach               # print the job id and return
  cellgate submit mill-1 O1234.nc --from-block N120      # start at block N120, its header first
  cellgate submit --resume mill-1-tpfqpi-3               # a failed job again, from its next block";

pub const PROGRAM: &str = "\
Examples:
  cellgate program put O1234 O1234.nc -c first-cut    # store a file as O1234's next revision
  cellgate program ls                                 # the library
  cellgate program get O1234 -o O1234.nc              # the latest revision, into a file
  cellgate program get O1234 --revision 2             # an earlier one, to standard output
  cellgate program history O1234                      # its revisions, newest first
  cellgate program diff O1234 1 2                     # two revisions, block by block
  cellgate program release O1234 -c proven            # the latest, released for production";

pub const STATUS: &str = "\
Examples:
  cellgate status                           # every machine, the PLCs, the gateway
  cellgate status mill-1 --json             # one machine, as JSON
  cellgate status -e tcp/10.0.3.7:7447      # the gateway of another host";

pub const WATCH: &str = "\
Examples:
  cellgate watch                            # every event of the cell, until Ctrl-C
  cellgate watch mill-1                     # one machine's
  cellgate watch plc-1 --tags=parts         # a PLC's, with its tag parts
  cellgate watch --json --count 10          # ten events as JSON, then exit";

pub const HISTORY: &str = "\
Examples:
  cellgate history --since 1h                      # the last hour, oldest first
  cellgate history mill-1 --kind job --newest      # mill-1's jobs, the last one first
  cellgate history --tag plc-1/parts --since 8h    # a tag's values
  cellgate history --since 2026-12-01T06:00:00Z --until 2026-12-01T14:00:00Z";

pub const PLC: &str = "\
Examples:
  cellgate plc read plc-1 D 10 --count 2         # two words of module D from address 10
  cellgate plc write plc-1 D 10 0x1234 65535     # two words written, confirmed by the PLC
  cellgate plc clear plc-1 D                     # the whole module D to 0
  cellgate plc status                            # stations, counters, poll groups, tags";

pub const RELOAD: &str = "\
Examples:
  cellgate reload               # read the cell file again and apply what changed
  cellgate reload --force       # changed machines restart at once (their running jobs fail)
  cellgate reload --json        # the gateway's ReloadResult";

pub const G05: &str = "\
Examples:
  cellgate g05 mill-2 examples/g05/circle.csv    # stream a file of blocks
  cellgate g05 mill-2 -                          # blocks from standard input (piped in)
  cellgate g05 mill-2 circle.csv --json          # the stream's last status as JSON";

pub const HISTORIAN: &str = "\
Examples:
  cellgate historian --database postgresql://cellgate@127.0.0.1/site           # every cell, until Ctrl-C
  cellgate historian --database postgresql://cellgate@127.0.0.1/site --status  # where each cell stands";
