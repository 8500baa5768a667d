complete -c plcsim -l bind -d 'UDP address to listen on' -r
complete -c plcsim -l pub -d 'User public file (variables, their addresses and types; its CRC becomes __PF_CRC). Default: the built-in demo file (conf/demo.pub). With --files, the PLC\'s file system serves it, read-only, at its root under its own name (as a PLC keeps it with its program)' -r -F
complete -c plcsim -l fixed -d 'Fixed public file; checked to place __PLC_RUN at S2.2 and __PF_CRC at S70' -r -F
complete -c plcsim -l files -d 'Directory served as the PLC\'s file system (paths confined to it). Without it, file services answer "service not activated"' -r -F
complete -c plcsim -l program -d 'PLC program: `demo` (manual chapter 6.1: dat, tim, c, sinus, cosinus, positive, text) or `idle` (none)' -r
complete -c plcsim -l animate -d 'Make every variable matching MASK change every cycle (`*` wildcard, case-insensitive; repeatable): integers ramp, reals follow a sine, BOOLs toggle, STRINGs count, times advance' -r
complete -c plcsim -l change-rate -d 'Change only this fraction of the animated variables per second, in turn (0.1 with 100,000 animated: 10,000 changes a second), each to a value it did not hold before; `status` on the control port counts them. Without it every animated variable changes every cycle' -r
complete -c plcsim -l devices -d 'Serve this many devices from one process, each with its own memory and program, on consecutive ports from the --bind, --modbus, --s7 or --ads port (Modbus: the first port also serves device k as unit id k). The control port\'s commands apply to all, or with `device <i>` to one' -r
complete -c plcsim -l loss -d 'Fraction of incoming packets to drop (0.0 - 1.0)' -r
complete -c plcsim -l latency -d 'Delay every answer by this many milliseconds' -r
complete -c plcsim -l control -d 'Loopback TCP address for run-time control (see below)' -r
complete -c plcsim -l cycle -d 'PLC cycle in milliseconds' -r
complete -c plcsim -l ident -d 'Identification string the PLC reports' -r
complete -c plcsim -l modbus -d 'Serve Modbus TCP on this address instead of EPSNET (coils, discrete inputs, holding and input registers; any unit id)' -r
complete -c plcsim -l s7 -d 'Serve S7comm over ISO-on-TCP on this address instead of EPSNET: an S7 CPU with DB1-DB16 and the merkers (any rack and slot; PDU up to 960)' -r
complete -c plcsim -l tags -d 'Modbus or S7 tag file (CSV) naming the variables the program and --animate drive. Default: the built-in conf/demo-modbus.csv (conf/demo-s7.csv with --s7)' -r -F
complete -c plcsim -l ads -d 'Serve Beckhoff ADS (AMS/TCP, e.g. 127.0.0.1:48898) on this address instead of EPSNET: the public file\'s variables as ADS symbols (by handle, sum commands, device notifications), ADS state RUN/STOP from HALT/RUN, a new symbol version with each `pub`' -r
complete -c plcsim -l serial -d 'Serve EPSNET on this serial device (a port, or one end of a pty pair: `socat -d -d pty,raw,echo=0,link=/tmp/plc pty,raw,echo=0,link=/tmp/srv`) instead of UDP. `--loss` then damages that fraction of the exchanges (answer lost, cut short, corrupted, or after noise)' -r
complete -c plcsim -l speed -d 'Serial line speed, baud (8N1, no flow control)' -r
complete -c plcsim -l emulate-line -d 'Hold each answer back for the time the request and the answer take on a real line at --speed (a pty passes bytes at memory speed)'
complete -c plcsim -s h -l help -d 'Print help (see more with \'--help\')'
complete -c plcsim -s V -l version -d 'Print version'
