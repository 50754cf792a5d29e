/* A raw, non-blocking pseudo-terminal for an emulated board's UART (the host board and the simavr
 * runner): the host opens its slave path as it would a USB serial device. */
#ifndef HBMA_PTY_H
#define HBMA_PTY_H

#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <termios.h>
#include <unistd.h>

/* Open the pty: its master (non-blocking) in *master, its slave kept open in *slave (so the master
 * never sees a hang-up when the host closes it), the slave's path in *name. 0 on success, else -1
 * after perror. */
static int open_raw_pty(int *master, int *slave, const char **name)
{
    *master = posix_openpt(O_RDWR | O_NOCTTY);
    if (*master < 0 || grantpt(*master) || unlockpt(*master)) {
        perror("pty");
        return -1;
    }
    *name = ptsname(*master);
    *slave = open(*name, O_RDWR | O_NOCTTY);
    struct termios tio;
    if (*slave < 0 || tcgetattr(*slave, &tio)) {
        perror("pty slave");
        return -1;
    }
    cfmakeraw(&tio);
    tcsetattr(*slave, TCSANOW, &tio);
    fcntl(*master, F_SETFL, O_NONBLOCK);
    return 0;
}

#endif
