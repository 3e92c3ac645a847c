/* The transport floor of overhead.py's `tcp-floor` variant: a TCP echo on 127.0.0.1.
 *
 * Listens on an ephemeral port of 127.0.0.1, prints the port on stdout, then serves one
 * connection at a time: every byte read is written back (TCP_NODELAY), in a blocking
 * loop, with no framing, parsing or allocation. What a training loop pays for one round
 * trip to it is what any remote shaping service pays at least on this machine: two
 * loopback sends and the wake-ups of a peer process that went idle, no gRPC, no HTTP/2,
 * no shaping. Built by overhead.py with the system C compiler (`cc -O2`). */
#include <arpa/inet.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <stdio.h>
#include <sys/socket.h>
#include <unistd.h>

int main(void) {
    int lfd = socket(AF_INET, SOCK_STREAM, 0);
    struct sockaddr_in addr = {0};
    addr.sin_family = AF_INET;
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    socklen_t len = sizeof addr;
    if (lfd < 0 || bind(lfd, (struct sockaddr *)&addr, sizeof addr) != 0 ||
        listen(lfd, 8) != 0 || getsockname(lfd, (struct sockaddr *)&addr, &len) != 0) {
        perror("tcp_echo");
        return 1;
    }
    printf("%d\n", ntohs(addr.sin_port));
    fflush(stdout);
    static char buf[1 << 16];
    for (;;) {
        int fd = accept(lfd, NULL, NULL);
        if (fd < 0) continue;
        int one = 1;
        setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
        ssize_t n;
        while ((n = read(fd, buf, sizeof buf)) > 0) {
            for (ssize_t off = 0; off < n;) {
                ssize_t w = write(fd, buf + off, (size_t)(n - off));
                if (w <= 0) break;
                off += w;
            }
        }
        close(fd);
    }
}
