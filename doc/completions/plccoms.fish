complete -c plccoms -s c -l config -d 'Configuration file' -r -F
complete -c plccoms -s l -l log -d 'Log file (without it, reports go to the terminal unless -d is given)' -r -F
complete -c plccoms -s d -l daemon -d 'Run in the background; reports go to the log file (PLCComS.log unless -l is given)'
complete -c plccoms -s t -l terminate -d 'Terminate if the configuration file was changed'
complete -c plccoms -s v -l verbose -d 'Verbose mode (multiple -v options increase the verbosity)'
complete -c plccoms -s h -l help -d 'Print help'
complete -c plccoms -s V -l version -d 'Print version'
