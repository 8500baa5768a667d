# Print an optspec for argparse to handle cmd's options that are independent of any subcommand.
function __fish_plccoms_global_optspecs
    string join \n d/daemon t/terminate v/verbose c/config= l/log= pid-file= h/help V/version
end

function __fish_plccoms_needs_command
    # Figure out if the current invocation already has a command.
    set -l cmd (commandline -opc)
    set -e cmd[1]
    argparse -s (__fish_plccoms_global_optspecs) -- $cmd 2>/dev/null
    or return
    if set -q argv[1]
        # Also print the command, so this can be used to figure out what it is.
        echo $argv[1]
        return 1
    end
    return 0
end

function __fish_plccoms_using_subcommand
    set -l cmd (__fish_plccoms_needs_command)
    test -z "$cmd"
    and return 1
    contains -- $cmd[1] $argv
end

complete -c plccoms -n "__fish_plccoms_needs_command" -s c -l config -d 'Configuration file' -r -F
complete -c plccoms -n "__fish_plccoms_needs_command" -s l -l log -d 'Log file (without it, reports go to the terminal unless -d is given)' -r -F
complete -c plccoms -n "__fish_plccoms_needs_command" -l pid-file -d 'Pid file, locked while the server runs (with -d: PLCComS.pid unless given; a file left by a crash is taken over)' -r -F
complete -c plccoms -n "__fish_plccoms_needs_command" -s d -l daemon -d 'Run in the background; reports go to the log file (PLCComS.log unless -l is given)'
complete -c plccoms -n "__fish_plccoms_needs_command" -s t -l terminate -d 'Terminate if the configuration file was changed (SIGHUP applies an edit without a restart)'
complete -c plccoms -n "__fish_plccoms_needs_command" -s v -l verbose -d 'Verbose mode (multiple -v options increase the verbosity)'
complete -c plccoms -n "__fish_plccoms_needs_command" -s h -l help -d 'Print help'
complete -c plccoms -n "__fish_plccoms_needs_command" -s V -l version -d 'Print version'
complete -c plccoms -n "__fish_plccoms_needs_command" -f -a "history" -d 'Write out what the historian recorded (CSV, JSON or Parquet)'
complete -c plccoms -n "__fish_plccoms_using_subcommand history" -l section -d 'Section whose history is read' -r
complete -c plccoms -n "__fish_plccoms_using_subcommand history" -l vars -d 'Variables: names or masks with *, comma-separated' -r
complete -c plccoms -n "__fish_plccoms_using_subcommand history" -l from -d 'Start (included): ISO 8601 UTC (2026-05-01T12:00:00Z, 2026-05-01) or relative (-1h, -7d)' -r
complete -c plccoms -n "__fish_plccoms_using_subcommand history" -l to -d 'End (excluded), as --from; default now' -r
complete -c plccoms -n "__fish_plccoms_using_subcommand history" -l format -d 'Output format' -r -f -a "csv\t''
json\t''
parquet\t''"
complete -c plccoms -n "__fish_plccoms_using_subcommand history" -l out -d 'Output file (default: standard output); written beside it and renamed at the end, never through a symbolic link' -r -F
complete -c plccoms -n "__fish_plccoms_using_subcommand history" -s c -l config -d 'Configuration file' -r -F
complete -c plccoms -n "__fish_plccoms_using_subcommand history" -l wide -d 'One row per time and one column per variable, instead of one row per sample'
complete -c plccoms -n "__fish_plccoms_using_subcommand history" -s h -l help -d 'Print help'
